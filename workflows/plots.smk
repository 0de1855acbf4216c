# Figures (PNG + PDF) from the run records, their renders and the recordings.


rule plots:
    input:
        records=eval_records(),
        recordings=[SUITE.recording_dir(s) for s in SUITE.scenes],
    output:
        [
            report(f, caption="report/figures.rst", category="Figures")
            if f.endswith(".png")
            else f
            for f in figure_files()
        ],
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/plots.log",
    params:
        out_dir=lambda wildcards, output: os.path.dirname(output[0]),
        qualitative=(
            f"--qualitative-scene {SUITE.qualitative_scene}"
            if SUITE.qualitative_scene
            else ""
        ),
    threads: res("plots", "threads")
    resources:
        mem_mb=res("plots", "mem_mb"),
    shell:
        "egobench plots --records {input.records} --recordings {input.recordings}"
        " --out-dir {params.out_dir} {params.qualitative} > {log} 2>&1"
