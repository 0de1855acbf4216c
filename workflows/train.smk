# One job per scene x method x seed. train.json (written last, atomically) marks a finished run;
# checkpoint.pt is not a declared output, so a failed job keeps it and a rerun resumes from it
# (--resume auto: a checkpoint of another config is replaced, not resumed).


rule train:
    input:
        recording=f"{R}/recordings/{{scene}}",
    output:
        record=f"{R}/runs/{{scene}}/{{method}}/seed{{seed}}/train.json",
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/train/{{scene}}/{{method}}/seed{{seed}}.log",
    benchmark:
        f"{R}/benchmarks/train/{{scene}}/{{method}}/seed{{seed}}.tsv"
    params:
        run_dir=lambda wildcards, output: os.path.dirname(output.record),
        args=lambda wildcards: SUITE.train_args(wildcards.scene),
    threads: res("train", "threads")
    resources:
        mem_mb=res("train", "mem_mb"),
        gpu=res("train", "gpu"),
        runtime=res("train", "runtime"),
    shell:
        "egobench train --recording {input.recording} --method {wildcards.method}"
        " --seed {wildcards.seed} --out {params.run_dir} {params.args} --resume auto > {log} 2>&1"
