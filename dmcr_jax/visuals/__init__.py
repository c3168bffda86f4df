"""Visual seeds for DMCR: batched `VisualParams`, texture banks, render models.

A visual seed (an int in [0, 2**31)) fixes a look; seed 0 is dm_control's.
`sample(domain, seeds, vary)` turns a batch of seeds into `VisualParams`
(jittable, one random stream per factor, bit-identical on every backend);
`build_render_model(domain)` compiles dm_control's model plus the texture bank
(procedural, built once and cached on disk, or a user's image folders);
`prepare`/`apply` write one env's look into that MuJoCo model cheaply, and
`render_frame` / `FrameRenderer` draw one frame with `mujoco.Renderer` — the
reference that batched render pools match; `look_at` moves looks within an
episode (a function of seed and step). `dmcr-show` renders a grid of looks.

Modules: `factors` (names, Table 5), `ranges` (per-domain data), `params`
(`VisualParams`, `sample`), `textures` (banks), `render_model` (render model,
apply, reference renderer), `moving` (looks that move within an episode), `show`
(the `dmcr-show` command).
"""

from dmcr_jax._lazy import lazy_names as _lazy_names

_LAZY = {
    **dict.fromkeys(("APPLICABLE", "DOMAINS", "FACTOR_IDS", "FACTORS", "active_factors",
                     "parse_vary"), "dmcr_jax.visuals.factors"),
    **dict.fromkeys(("VisualParams", "check_seeds", "defaults", "sample"),
                    "dmcr_jax.visuals.params"),
    **dict.fromkeys(("FrameRenderer", "Looks", "RenderModel", "apply", "build_render_model",
                     "close_renderers", "prepare", "render_frame", "set_skybox"),
                    "dmcr_jax.visuals.render_model"),
    **dict.fromkeys(("MOVING_FACTORS", "check_moving", "look_at"), "dmcr_jax.visuals.moving"),
    **dict.fromkeys(("NUM_BACKGROUNDS", "NUM_FLOORS", "TextureBank", "cache_dir",
                     "load_bank"), "dmcr_jax.visuals.textures"),
}
"""Where the names below live; each module is imported on first use (a worker
process that only needs `dmcr_jax.visuals.pool` loads neither JAX nor MuJoCo)."""

__getattr__, __dir__ = _lazy_names(__name__, _LAZY, globals())


__all__ = [
    "APPLICABLE", "DOMAINS", "FACTORS", "FACTOR_IDS", "FrameRenderer", "Looks",
    "MOVING_FACTORS", "NUM_BACKGROUNDS", "NUM_FLOORS", "RenderModel", "TextureBank",
    "VisualParams", "active_factors", "apply", "build_render_model",
    "cache_dir", "check_moving", "check_seeds", "close_renderers", "defaults", "load_bank",
    "look_at", "parse_vary", "prepare", "render_frame", "sample", "set_skybox",
]
