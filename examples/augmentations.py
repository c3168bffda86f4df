"""An augmentation of your own: a random hue rotation, for `dmcr-train --aug`.

    dmcr-train --task cartpole-balance --aug drq,cj+drq,examples.augmentations:hue_rotation+drq

See docs/augmentations.md. Like every built-in, it is written for ONE sample.
"""

import jax
import jax.numpy as jnp

from dmcr_jax import augment


def hue_rotation(key, image):
  """Rotates the hue of one uint8 (H, W, 3·stack) observation by a random angle.

  The angle is uniform over [−0.5, 0.5) turns, one draw per sample, the same
  for every frame of the stack; saturation and value are kept.
  """
  turns = jax.random.uniform(key, (), minval=-0.5, maxval=0.5)
  x = image.astype(jnp.float32) / 255.0
  h, s, v = augment.rgb_to_hsv(x[..., 0::3], x[..., 1::3], x[..., 2::3])  # per frame
  rgb = jnp.stack(augment.hsv_to_rgb(h + turns, s, v), axis=-1).reshape(image.shape)
  return jnp.clip(jnp.round(rgb * 255.0), 0, 255).astype(jnp.uint8)
