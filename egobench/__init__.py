"""egobench: reproduce, measure and extend egocentric photoreal scene reconstruction.

One library holds the science (geometry, cameras, image formation, rasterizer, simulator,
trainer, evaluation, diagnosis); a thin Snakemake workflow wires it into a DAG.
"""

__version__ = "0.1.0"
