# Held-out evaluation of one run: writes the run record eval.json (schema egobench.run/1) and the
# renders beside it; eval.json is written last, atomically.


rule evaluate:
    input:
        recording=f"{R}/recordings/{{scene}}",
        train=f"{R}/runs/{{scene}}/{{method}}/seed{{seed}}/train.json",
    output:
        record=f"{R}/runs/{{scene}}/{{method}}/seed{{seed}}/eval.json",
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/evaluate/{{scene}}/{{method}}/seed{{seed}}.log",
    benchmark:
        f"{R}/benchmarks/evaluate/{{scene}}/{{method}}/seed{{seed}}.tsv"
    params:
        run_dir=lambda wildcards, output: os.path.dirname(output.record),
        args=lambda wildcards: SUITE.evaluate_args(wildcards.scene),
    threads: res("evaluate", "threads")
    resources:
        mem_mb=res("evaluate", "mem_mb"),
        gpu=res("evaluate", "gpu"),
        runtime=res("evaluate", "runtime"),
    shell:
        "egobench evaluate --recording {input.recording} --run {params.run_dir}"
        " {params.args} > {log} 2>&1"
