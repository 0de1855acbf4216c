# One synthetic recording per scene, built in a hidden .<scene>.partial/ folder beside the output and
# renamed on success; a failed or killed job leaves that partial folder, and the rerun continues it
# from its last complete frame (byte-identical to an uninterrupted run; egobench.sim.capture).


rule simulate:
    wildcard_constraints:
        scene=SUITE.scene_regex(SUITE.simulated_scenes()),
    output:
        directory(f"{R}/recordings/{{scene}}"),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/simulate/{{scene}}.log",
    benchmark:
        f"{R}/benchmarks/simulate/{{scene}}.tsv"
    params:
        args=lambda wildcards: SUITE.simulate_args(wildcards.scene),
    threads: res("simulate", "threads")
    resources:
        mem_mb=res("simulate", "mem_mb"),
        gpu=res("simulate", "gpu"),
        runtime=res("simulate", "runtime"),
    shell:
        "egobench simulate --out {output} {params.args} > {log} 2>&1"
