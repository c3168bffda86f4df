"""Jit-compiled, deterministic image augmentations of the DMCR paper's appendix.

The eleven augmentations of the appendix's "Augmentation Comparison" plus the
two "alterations" of the main results (Sec. 2 and 5, Table 3) and the paper's
pipelines SAC+AUG, SAC+CJ+AUG and SAC+NR+AUG (Sec. 3.2: CJ or NR, then the DrQ
crop). `get(name)` returns one; `NAMES` lists them; ``"a+b"`` applies a, then b.
Call it as ``aug(key, obs)`` or ``aug(key, (obs, next_obs))`` (any pytree):
uint8 images ``(B, H, W, 3·stack)``, channels-last, in; same shapes, uint8, out.

- ``rad``: RAD, zoom 84→100 and a random 84×84 crop (appendix item 1);
- ``cutout_color``: Cutout Color (2);
- ``drq``, ``drq_no_noise``: DrQ, 4-px replicate pad and crop, ± noise (3, 4);
- ``large_drq``, ``large_drq_no_noise``: the same with 12 px (5, 6);
- ``translate``, ``large_translate``: shift in a 4/12-px random-colour border (7, 8);
- ``rotate``: by 0, 90, 180 or 270° (9);
- ``vertical_flip``: 180° rotation of part of the batch (10);
- ``window``: a lens shows the image, 0 elsewhere (11);
- ``cj``, ``nr``: Color Jitter, Network Randomization;
- ``drq``, ``cj+drq``, ``nr+drq``: the pipelines of SAC+AUG, SAC+CJ+AUG, SAC+NR+AUG;
- ``none``: the identity (for baselines and benchmarks).

Your own augmentation: write it for ONE sample, ``fn(key, image) -> image`` on a
uint8 ``(H, W, 3·stack)`` image (the built-ins' convention, see below), then
``register("mine", fn)`` so that `get`, ``"mine+drq"``, `SACConfig.aug` and
``dmcr-train --aug`` know it, or name it by import path, ``"package.module:function"``
(`load`), which every one of those accepts too. `check` runs the properties the
learner relies on against real rendered observations (`dmcr_jax.augment_check`).

Randomness (appendix: identical for a sample's o and o′ and for the frames of its
stack; deterministically seeded): each augmentation is written for ONE sample as
``sample(key, (H, W)) -> params`` and ``apply(params, image (H, W, C)) -> image``.
Parameters never depend on C, so every frame of the stack gets them; the batch is
a `jax.vmap` at the edge; every array of a pytree is transformed with the same
parameters. Sample i draws from ``fold_in(key, i)`` (`sample_keys`), so its draw
does not depend on the batch size; Network Randomization draws one convolution
per call from ``key``. The same key gives bit-identical output on a backend:
integer arithmetic, or float32 rounded half to even.

Image sizes: every default is the paper's value for 84×84 images. Shifts (DrQ's
and Translate's pads) stay in pixels at any size; RAD zooms by 100/84; occluders
(Cutout Color's box, Window's lens) scale with the side, ``round(v · side / 84)``.
Rotate needs square images (ValueError otherwise). Where the paper gives no
value, each factory's docstring says which original (RAD, DrQ, NR, or DMCR's code
release) it follows.

Where things live: the types and their batching in `augment_core`, the random
words in `augment_random`, the spatial augmentations in `augment_spatial`, Color
Jitter and Network Randomization in `augment_color`, the names (`get`, `register`,
`load`) in `augment_registry`; this module re-exports their public names.
"""

# The modules' public names, re-exported for callers (the library's own modules
# import them from their homes).
from dmcr_jax.augment_color import (NR_INIT_STD, color_jitter, hsv_to_rgb,
                                    network_randomization, rgb_to_hsv)
from dmcr_jax.augment_core import (ApplyFn, Augmentation, Composed, Images, Params,
                                   SampleFn, identity, sample_keys)
from dmcr_jax.augment_registry import (NAMES, SampleAugFn, check, from_function, get, load,
                                       register, registered, unregister)
from dmcr_jax.augment_spatial import (cutout_color, drq, rad, rotate, translate,
                                      vertical_flip, window)
