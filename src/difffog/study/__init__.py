"""Application code on top of the solvers: the speed–accuracy study (``difffog bench``), the
shipped independent references (:mod:`difffog.study.references`) and the slab validation
problem (``_slab.py``)."""

from ._slab import slab_problem as slab_problem, slab_reflectance as slab_reflectance
