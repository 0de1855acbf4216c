"""The file names the report steps write (the workflow's targets), without the libraries that write them:
the Snakefile reads these at parse time, and pandas and matplotlib cost every `snakemake` call ~0.5 s."""

from __future__ import annotations

#: Every file `egobench.report.tables.write_tables` produces, relative to its output folder.
TABLE_FILES = (
    "results.csv",
    "table1_outdoor.csv",
    "table1_outdoor.tex",
    "table1_indoor.csv",
    "table1_indoor.tex",
    "table1.tex",
    "table2.csv",
    "table2.tex",
    "table3.csv",
    "table3.tex",
    "table4.csv",
    "table4.tex",
    "gains.csv",
    "gains.tex",
)
#: The figures of `egobench.report.plots.make_plots`, and every file it writes (each figure as png and
#: pdf, and notes.json).
FIGURES = ("gains", "psnr_vs_head_speed", "qualitative", "motion_displacement", "gain3x")
FIGURE_FILES = tuple(f"{name}.{ext}" for name in FIGURES for ext in ("png", "pdf")) + ("notes.json",)
