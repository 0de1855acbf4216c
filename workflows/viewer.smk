# The researcher's view of a trained scene: per scene, the first seed of 'ours' as an INRIA 3DGS
# PLY (SuperSplat, viser, nerfstudio open it), a side-by-side fly-through video (ours, w/o motion
# sampling when the scene trains it, the captured frames) and a self-contained viewer page (WebGL,
# the camera's own exposure, the same two runs) that the HTML report links.


rule export_ply:
    input:
        record=lambda wildcards: f"{SUITE.viewer_runs(wildcards.scene)[0]}/eval.json",
    output:
        ply=f"{R}/viewer/{{scene}}/ours.ply",
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/viewer/{{scene}}/export.log",
    params:
        run_dir=lambda wildcards, input: os.path.dirname(input.record),
    threads: res("viewer", "threads")
    resources:
        mem_mb=res("viewer", "mem_mb"),
    shell:
        "egobench export {params.run_dir} --ply {output.ply} > {log} 2>&1"


rule render_video:
    input:
        recording=f"{R}/recordings/{{scene}}",
        records=lambda wildcards: [f"{r}/eval.json" for r in SUITE.viewer_runs(wildcards.scene) if r],
    output:
        video=report(f"{R}/viewer/{{scene}}/flythrough.mp4", caption="report/viewer.rst", category="Fly-through"),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/viewer/{{scene}}/render.log",
    params:
        run_dir=lambda wildcards, input: os.path.dirname(input.records[0]),
        args=lambda wildcards: SUITE.render_args(wildcards.scene),
    threads: res("viewer", "threads")
    resources:
        mem_mb=res("viewer", "mem_mb"),
        gpu=res("viewer", "gpu"),
    shell:
        "egobench render {params.run_dir} --recording {input.recording} --video {output.video}"
        " {params.args} --no-progress > {log} 2>&1"


rule view_page:
    input:
        recording=f"{R}/recordings/{{scene}}",
        records=lambda wildcards: [f"{r}/eval.json" for r in SUITE.viewer_runs(wildcards.scene) if r],
    output:
        page=report(f"{R}/viewer/{{scene}}/view/index.html", caption="report/viewer_page.rst", category="Viewer"),
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/viewer/{{scene}}/view.log",
    params:
        run_dir=lambda wildcards, input: os.path.dirname(input.records[0]),
        out=lambda wildcards, output: os.path.dirname(output.page),
        args=lambda wildcards: SUITE.view_args(wildcards.scene),
    threads: res("viewer", "threads")
    resources:
        mem_mb=res("viewer", "mem_mb"),
    shell:
        "egobench view {params.run_dir} --recording {input.recording} --out {params.out} {params.args} > {log} 2>&1"
