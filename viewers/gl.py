"""The OpenGL context of the viewers: a standalone moderngl context on EGL (headless, no display needed).

Both the previews (:mod:`viewers.preview`) and the shader checks (:mod:`viewers.shading_glsl`) create their context
here, so neither imports the other.
"""

from __future__ import annotations

from toolkit._checks import DarsError

__all__ = ["create_headless_context"]


def create_headless_context(require: int = 330):
    """A standalone moderngl context on EGL (no display needed; Mesa llvmpipe without a GPU).

    Raises:
        DarsError: when no EGL/OpenGL 3.3 context can be created, saying which system packages provide it.
    """
    import moderngl

    try:
        return moderngl.create_standalone_context(backend="egl", require=require)
    except Exception as e:  # moderngl raises plain Exception subclasses from glcontext
        raise DarsError(f"could not create a headless OpenGL {require // 100}.{require % 100 // 10} context on EGL "
                        f"({e}); install libegl1 libegl-mesa0 libgl1-mesa-dri (scripts/setup.sh does) or run "
                        "under `xvfb-run -a`") from e
