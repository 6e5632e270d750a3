"""synth: a thin-lens renderer whose defocus blur is known exactly.

    >>> import synth
    >>> result = synth.render("data_specs/scenes/demo.toml")   # doctest: +SKIP
    >>> synth.write_stack(result, "out/demo")                   # doctest: +SKIP

Layout follows the data flow: ``scene`` (spec -> shots) -> ``geometry`` (camera and poses)
-> ``raytrace`` / ``convolve`` (render methods) -> ``rendering`` (pipeline, truth; ``synth.render``) -> ``stack``
(writer).
"""

import lazy_loader

from lensfit import __version__


__getattr__, __dir__, __all__ = lazy_loader.attach(  # lazy: importing synth does not import JAX
    __name__, submod_attrs={"rendering": ["render", "plan"], "scene": ["load_scene"], "stack": ["write_stack"]})
__all__ = ["__version__", *__all__]
