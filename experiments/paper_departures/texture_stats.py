"""Structure of the held-out skies in the frame: mean |gradient| (px-to-px luminance difference,
0-255) and within-frame luminance std over the sky pixels (segmentation), training frame vs
held-out looks; ours (procedural) vs the original's photos (same geometry, bg_probe frames)."""
import numpy as np
for dom in ("cheetah", "hopper"):
  z = np.load(f"{dom}_frames.npz"); seg = z["seg"]; sky = seg == -1
  for name in ("ours", "photos"):
    F = z[name].astype(np.float32).mean(-1)            # (S, 1+N, 84, 84) luminance
    gx = np.abs(np.diff(F, axis=-1))[..., :-1, :]; gy = np.abs(np.diff(F, axis=-2))[..., :, :-1]
    g = gx + gy                                        # (S, 1+N, 83, 83)
    m = (sky[:, :-1, :-1] & sky[:, 1:, :-1] & sky[:, :-1, 1:])[:, None]
    mm = np.broadcast_to(m, g.shape)
    grad = lambda sl: g[:, sl][mm[:, sl]].mean()
    std = np.array([[F[s, i][sky[s]].std() for i in range(F.shape[1])] for s in range(F.shape[0])])
    print(f"{dom:8s} {name:7s} sky |grad| train {grad(slice(0,1)):5.2f}  looks {grad(slice(1,None)):5.2f} | "
          f"sky luminance std train {std[:,0].mean():5.1f}  looks {std[:,1:].mean():5.1f}")
