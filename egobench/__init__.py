"""egobench: reproduce, measure and extend egocentric photoreal scene reconstruction.

One library holds the science (geometry, cameras, image formation, rasterizer, simulator,
trainer, evaluation, diagnosis); a thin Snakemake workflow wires it into a DAG.
"""

__version__ = "0.1.0"

from egobench.host import cap_numba_pool as _cap_numba_pool

_cap_numba_pool()  # before any egobench module loads numba (Snakemake's one thread per job)
