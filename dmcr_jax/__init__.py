"""dmcr_jax: DeepMind Control Remastered as a massively batched JAX system.

Physics is dm_control's own suite models stepped by vmapped MJX
(`dmcr_jax.models`); visual seeds become batched render parameters
(`dmcr_jax.visuals`). `ALL_TASKS` lists the 22 DMCR tasks.
"""

from dmcr_jax.models import ALL_TASKS, DOMAIN_TASKS, load

__version__ = "0.1.0"
__all__ = ["ALL_TASKS", "DOMAIN_TASKS", "load", "__version__"]
