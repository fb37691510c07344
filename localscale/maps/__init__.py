"""Scale maps at full resolution: read out band by band from the network's processing grid in
bounded memory (:mod:`.grid`, :class:`GridMaps`), and written as files (:mod:`.files`: ``.npy``,
float TIFF, colour PNG, ``geometry.json``)."""

from .grid import BAND_ELEMENTS, GridMaps

__all__ = ["BAND_ELEMENTS", "GridMaps"]
