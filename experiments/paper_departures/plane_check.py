"""Is widening cheetah's ground (size "100 .8 .5" -> "100 15 .5", as the original does) physics-
neutral? Steps dm_control's cheetah MJCF both ways with the same random actions and compares."""
import numpy as np, mujoco
from dm_control.suite import cheetah, common
xml, assets = cheetah.get_model_and_assets()
wide = xml.decode().replace('size="100 .8 .5"', 'size="100 15 .5"').encode()
assert wide != xml
ms = [mujoco.MjModel.from_xml_string(x.decode(), assets) for x in (xml, wide)]
ds = [mujoco.MjData(m) for m in ms]
rng = np.random.default_rng(0)
for t in range(5000):
  a = rng.uniform(-1, 1, ms[0].nu)
  if t % 1000 == 0:
    for d in ds: d.qpos[3:] = rng.uniform(-0.5, 0.5, ms[0].nq - 3) * 0 + d.qpos[3:]
  for m, d in zip(ms, ds): d.ctrl[:] = a; mujoco.mj_step(m, d)
print("max |qpos diff| after 5000 steps:", np.abs(ds[0].qpos - ds[1].qpos).max(),
      "| ncon", ds[0].ncon, ds[1].ncon, "| rootx", ds[0].qpos[0])
