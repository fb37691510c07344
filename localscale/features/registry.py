"""The registry of local feature extractors: name -> :class:`~.extractors.Extractor` subclass.

Each extractor class declares its name, options, weight files, LightGlue weights, working size,
what it needs installed and its named matchers (:class:`~.extractors.Extractor`); registering it
makes it, and its matchers, known to :class:`~localscale.matching.MatchConfig`,
:data:`~localscale.matching.MATCHERS`, ``localscale match --matcher`` and ``reconstruct``.
The extractors of localscale are the modules of :mod:`.extractors`, registered when that package is
imported (:mod:`localscale.matching` imports it); this module imports none of them.

Example::

    @register
    class ORB(Extractor):
        name = "orb"
        default_conf = {"num_features": 2000}
        def _extract(self, image): ...

    match_pair("a.jpg", "b.jpg", "none", matcher="orb")
"""

from __future__ import annotations

from ..core.errors import LocalScaleError

#: extractor name -> class, in registration order
EXTRACTORS: dict[str, type] = {}


def matchers_of(cls: type) -> dict:
    """The named matchers of an extractor class: name -> MatchConfig options."""
    return dict(cls.matchers) if cls.matchers is not None else {cls.name: {}}


def named_matchers() -> dict:
    """Every registered extractor's named matchers: name -> (extractor class, MatchConfig options),
    in registration order."""
    return {m: (cls, opts) for cls in EXTRACTORS.values() for m, opts in matchers_of(cls).items()}


def register(cls: type) -> type:
    """Add an :class:`~.extractors.Extractor` subclass under its ``name`` (a class decorator);
    returns it. A name or matcher name that another class holds is refused."""
    if not (isinstance(cls, type) and any(c.__name__ == "Extractor" for c in cls.__mro__[1:])):
        raise LocalScaleError(f"register takes an Extractor subclass, got {cls!r}")
    if not isinstance(cls.name, str) or not cls.name:
        raise LocalScaleError(f"{cls.__name__}.name must be a non-empty string, got {cls.name!r}")
    if EXTRACTORS.get(cls.name, cls) is not cls:
        raise LocalScaleError(f"extractor name {cls.name!r} is taken by {EXTRACTORS[cls.name].__name__}")
    if not isinstance(cls.default_conf, dict):
        raise LocalScaleError(f"{cls.__name__}.default_conf must be a dict")
    taken = {m: other for other in EXTRACTORS.values() if other is not cls for m in matchers_of(other)}
    for m in matchers_of(cls):
        if m in taken:
            raise LocalScaleError(f"matcher name {m!r} of {cls.__name__} is taken by {taken[m].__name__}")
    EXTRACTORS[cls.name] = cls
    return cls


def get_extractor(name: str) -> type:
    """The registered class called ``name``."""
    if name not in EXTRACTORS:
        raise LocalScaleError(f"extractor must be one of {tuple(EXTRACTORS)}, got {name!r}")
    return EXTRACTORS[name]


def weight_files() -> dict:
    """Every weight file of the registered extractors and their LightGlue: file name -> ``WeightFile``."""
    out = {}
    for cls in EXTRACTORS.values():
        for f in (*cls.weights, cls.lightglue_weights):
            if f is not None:
                out.setdefault(f.filename, f)
    return out
