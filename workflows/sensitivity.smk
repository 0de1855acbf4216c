# `snakemake --cores 2 sensitivity` (not part of `all`): per ablation of config.sensitivity, one
# recording per swept value (sens-<ablation>-<value>), 'ours' and the ablation trained with every
# seed by the ordinary simulate / train / evaluate rules, the recording's measured effect size
# (`egobench similarity`), then ΔPSNR against it, with the paper-scale Δ read off a fitted curve
# (`egobench sensitivity`; docs/workflow.md). The sweeps' SimConfig overrides are checked when this
# target is asked for (sensitivity_targets, common.smk).


rule sensitivity:
    input:
        sensitivity_targets,


# The measured effect sizes of one recording (rolling-shutter shift, calibration error, dynamic
# range, ...). The one place that calls `egobench similarity`.
rule sensitivity_similarity:
    wildcard_constraints:
        scene=SUITE.scene_regex(list(SUITE.sensitivity_scenes)),
    input:
        recording=f"{R}/recordings/{{scene}}",
    output:
        json=f"{R}/sensitivity/similarity/{{scene}}.json",
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/sensitivity/similarity/{{scene}}.log",
    threads: res("similarity", "threads")
    resources:
        mem_mb=res("similarity", "mem_mb"),
    shell:
        "if ! egobench similarity --help > /dev/null 2>&1; then"
        " echo 'egobench has no similarity verb (egobench similarity REC --out FILE.json, issue 13):"
        " the sensitivity curves need the measured effect size of each recording' | tee {log} >&2; exit 1; fi;"
        " egobench similarity {input.recording} --out {output.json} --no-progress > {log} 2>&1"


rule sensitivity_curves:
    input:
        records=SUITE.sensitivity_records(),
        similarity=SUITE.sensitivity_similarity(),
    output:
        [
            report(f, caption="report/sensitivity.rst", category="Sensitivity")
            if f.endswith((".png", ".csv"))
            else f
            for f in wc.sensitivity_workflow.output_files(R)
        ],
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/sensitivity/curves.log",
    params:
        out_dir=lambda wildcards, output: os.path.dirname(output[0]),
        args=SUITE.sensitivity_args(),
    threads: res("tables", "threads")
    resources:
        mem_mb=res("tables", "mem_mb"),
    shell:
        "egobench sensitivity --records {input.records} --similarity {input.similarity}"
        " --out-dir {params.out_dir} {params.args} > {log} 2>&1"
