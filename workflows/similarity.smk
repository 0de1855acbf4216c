# How close each recording sits to the paper's operating point: the pixel-scale quantities that decide
# each finding (egobench similarity; docs/similarity.md).


rule similarity:
    input:
        recordings=[f"{R}/recordings/{s}" for s in sorted(SUITE.scenes)],
    output:
        json=f"{R}/similarity/similarity.json",
        csv=f"{R}/similarity/similarity.csv",
        table=f"{R}/similarity/similarity.md",
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/similarity.log",
    threads: res("similarity", "threads")
    resources:
        mem_mb=res("similarity", "mem_mb"),
    shell:
        "egobench similarity {input.recordings} --out {output.json} --csv {output.csv} "
        "--table {output.table} --no-progress > {log} 2>&1"
