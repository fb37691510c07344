"""Scale maps at full resolution: read out band by band from the network's processing grid in
bounded memory (:mod:`.grid`, :class:`GridMaps`), and written as files (:mod:`.files`: ``.npy``,
float TIFF, colour PNG, ``geometry.json``)."""

from ..core.lazy import lazy_exports

_EXPORTS = {".grid": ("BAND_ELEMENTS", "GridMaps")}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
