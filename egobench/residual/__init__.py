"""What a residual between measured and predicted images can show: the signatures of physical
effects (`signatures`: image operators, the diagnosis context, the frame-level tests) and the
machinery that tests a candidate cause in a residual (`estimation`: `ResidualData`, the joint
photometric regression, the geometric first-order fit and refinement, `CauseResult`). Each
effect's own estimator lives in its file under egobench/effects/; the diagnosis
(egobench.diagnose) runs the library of them."""
