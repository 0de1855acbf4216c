# Residual diagnosis of a recording under one method; and (optionally) head-motion statistics.


rule diagnose:
    input:
        recording=f"{R}/recordings/{{scene}}",
        run=lambda wildcards: SUITE.diagnose_run(wildcards.scene, wildcards.method),
    output:
        report(
            directory(f"{R}/diagnosis/{{scene}}/{{method}}"),
            caption="report/diagnose.rst",
            category="Diagnosis",
            patterns=["{name}.png"],
        ),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/diagnose/{{scene}}/{{method}}.log",
    benchmark:
        f"{R}/benchmarks/diagnose/{{scene}}/{{method}}.tsv"
    params:
        args=lambda wildcards: SUITE.diagnose_args(wildcards.scene, wildcards.method),
    threads: res("diagnose", "threads")
    resources:
        mem_mb=res("diagnose", "mem_mb"),
        gpu=res("diagnose", "gpu"),
        runtime=res("diagnose", "runtime"),
    shell:
        "egobench diagnose {input.recording} --method {wildcards.method}"
        " --out {output} {params.args} > {log} 2>&1"


rule motion_stats:
    output:
        json=report(
            f"{R}/motion_stats/motion_stats.json",
            caption="report/motion_stats.rst",
            category="Motion",
        ),
        csv=f"{R}/motion_stats/motion_stats.csv",
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/motion_stats.log",
    params:
        out_dir=lambda wildcards, output: os.path.dirname(output.json),
        args=SUITE.motion_stats_args(),
    threads: res("motion_stats", "threads")
    resources:
        mem_mb=res("motion_stats", "mem_mb"),
    shell:
        "egobench motion-stats --out {params.out_dir} {params.args} > {log} 2>&1"


# `snakemake --cores 2 discovery` (not part of `all`): the hidden-effect sweep (every effect x
# several magnitudes x seeds, plus null cases: detection and false-alarm rates, parameter error,
# PSNR gain) and, when config.diagnose.adt_dir is set, the Aria Digital Twin real-vs-twin diagnosis.
rule discovery:
    input:
        SUITE.discovery_outputs(),


rule diagnose_sweep:
    output:
        report(
            directory(f"{R}/discovery/sweep"),
            caption="report/diagnose.rst",
            category="Diagnosis",
            patterns=["{name}.md"],
        ),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/discovery/sweep.log",
    benchmark:
        f"{R}/benchmarks/discovery/sweep.tsv"
    params:
        seeds=SUITE.sweep_seeds,
    threads: res("diagnose", "threads")
    resources:
        mem_mb=res("diagnose", "mem_mb"),
    shell:
        "egobench diagnose --sweep --sweep-seeds {params.seeds} --out {output} --no-progress > {log} 2>&1"


# config.diagnose.trained_sweep.enabled: the sweep on trained runs. The outputs are the tables only,
# so the per-case folders (cases/: recording, run, diagnosis) survive a failed or interrupted job
# and a rerun redoes only the unfinished cases.
rule diagnose_trained_sweep:
    output:
        json=f"{R}/discovery/trained_sweep/trained_sweep.json",
        csv=f"{R}/discovery/trained_sweep/trained_sweep.csv",
        md=report(f"{R}/discovery/trained_sweep/trained_sweep.md", caption="report/diagnose.rst", category="Diagnosis"),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/discovery/trained_sweep.log",
    benchmark:
        f"{R}/benchmarks/discovery/trained_sweep.tsv"
    params:
        args=SUITE.trained_sweep_args(),
        out_dir=lambda wildcards, output: os.path.dirname(output.json),
    threads: res("diagnose", "threads")
    resources:
        mem_mb=res("diagnose", "mem_mb"),
    shell:
        "egobench diagnose --sweep --trained {params.args} --out {params.out_dir} --no-progress > {log} 2>&1"


rule diagnose_adt:
    output:
        report(
            directory(f"{R}/discovery/adt"),
            caption="report/diagnose.rst",
            category="Diagnosis",
            patterns=["{name}.png"],
        ),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/discovery/adt.log",
    params:
        adt=SUITE.adt_dir or "",
    threads: res("diagnose", "threads")
    resources:
        mem_mb=res("diagnose", "mem_mb"),
    shell:
        "egobench diagnose --adt {params.adt} --out {output} --no-progress > {log} 2>&1"
