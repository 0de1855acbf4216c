# A real scene (source: aria, or aria_root + aria_scene): `egobench preprocess` rectifies the VRS with
# its MPS output into the recording folder, in the authors' layout (the online-calibration stream, and
# the factory one when a method of the scene needs it). An interrupted preprocess resumes from its
# partial folder beside the output (egobench.data.preprocess).


rule preprocess:
    wildcard_constraints:
        scene=SUITE.scene_regex(SUITE.aria_scenes()),
    input:
        vrs=lambda wildcards: SUITE.aria_input(wildcards.scene, "vrs"),
        mps=lambda wildcards: SUITE.aria_input(wildcards.scene, "mps"),
    output:
        directory(f"{R}/recordings/{{scene}}"),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/preprocess/{{scene}}.log",
    benchmark:
        f"{R}/benchmarks/preprocess/{{scene}}.tsv"
    params:
        args=lambda wildcards: SUITE.preprocess_args(wildcards.scene),
        factory=lambda wildcards: "--factory-calibration" if SUITE.needs_factory_stream(wildcards.scene) else "",
    threads: res("preprocess", "threads")
    resources:
        mem_mb=res("preprocess", "mem_mb"),
        gpu=res("preprocess", "gpu"),
        runtime=res("preprocess", "runtime"),
    shell:
        "egobench preprocess {input.vrs} --mps {input.mps} --out {output} {params.args} --no-progress > {log} 2>&1"
        " && if [ -n '{params.factory}' ]; then egobench preprocess {input.vrs} --mps {input.mps} --out {output}"
        " {params.args} {params.factory} --no-progress >> {log} 2>&1; fi"
