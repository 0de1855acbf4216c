"""Residual diagnosis (issue 6): what a model gets wrong about measured data, named by its physical
signature, estimated, modelled, and the held-out gain measured.

API:
    diagnose_residuals(measured, predicted, context, config) -> Diagnosis   (egobench.diagnose.core)
    ground_truth_source(recording) / run_source(recording, run_dir) -> Sources  (egobench.diagnose.sources)
    write_report(out_dir, diagnosis, measured, predicted)                  (egobench.diagnose.report)
    run_sweep(out_dir) (egobench.diagnose.sweep), diagnose_adt(adt_dir, out_dir) (egobench.diagnose.adt)

CLI (`egobench.diagnose.cli`): ``egobench diagnose RECORDING --method M --out DIR [--run RUN_DIR | --train] [--source ...]``,
``egobench diagnose --sweep --out DIR``, ``egobench diagnose --adt ADT_DIR --out DIR``.
"""

from __future__ import annotations

from egobench.diagnose.core import NO_DISCREPANCY, Diagnosis, DiagnosisConfig, NamedCause, diagnose_residuals
from egobench.residual.signatures import DiagnosisContext

__all__ = ["NO_DISCREPANCY", "Diagnosis", "DiagnosisConfig", "DiagnosisContext", "NamedCause", "diagnose_residuals"]
