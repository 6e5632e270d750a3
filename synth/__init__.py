"""synth: a thin-lens renderer whose defocus blur is known exactly.

    >>> import synth
    >>> result = synth.render("data_specs/scenes/demo.toml")   # doctest: +SKIP
    >>> synth.write_stack(result, "out/demo")                   # doctest: +SKIP

Layout follows the data flow: ``scene`` (spec -> shots) -> ``geometry`` (camera and poses)
-> ``raytrace`` / ``convolve`` (render methods) -> ``render`` (pipeline, truth) -> ``stack``
(writer).
"""

from lensfit import __version__

__all__ = ["__version__", "render", "plan", "load_scene", "write_stack"]


def __getattr__(name):  # lazy: importing synth does not import JAX
    if name in ("render", "plan"):
        import importlib

        # synth.render is also the module's name; importing it makes the attribute the module,
        # which is callable (synth/render.py) so that synth.render(...) works either way.
        module = importlib.import_module("synth.render")
        return module if name == "render" else module.plan
    if name == "load_scene":
        from synth.scene import load_scene

        return load_scene
    if name == "write_stack":
        from synth.stack import write_stack

        return write_stack
    raise AttributeError(f"module 'synth' has no attribute {name!r}")
