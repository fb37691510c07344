"""The ground every other module stands on: the errors raised for bad input (:mod:`.errors`),
atomic output files (:mod:`.outputs`), torch device names (:mod:`.devices`), checks of option
values (:mod:`.checks`) and lazy package exports (:mod:`.lazy`). Nothing here imports the rest
of localscale at import time."""
