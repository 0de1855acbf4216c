# One synthetic recording per scene (written atomically by the verb: a failed job leaves no folder).


rule simulate:
    output:
        directory(f"{R}/recordings/{{scene}}"),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/simulate/{{scene}}.log",
    benchmark:
        f"{R}/benchmarks/simulate/{{scene}}.tsv"
    params:
        eb=EGOBENCH,
        args=lambda wildcards: SUITE.simulate_args(wildcards.scene),
    threads: res("simulate", "threads")
    resources:
        mem_mb=res("simulate", "mem_mb"),
        gpu=res("simulate", "gpu"),
        runtime=res("simulate", "runtime"),
    shell:
        "{params.eb} simulate --out {output} {params.args} > {log} 2>&1"
