"""The Snakemake glue: the suite config, the sensitivity sweep's config and the SLURM report."""
