# Paper-shaped tables (CSV + LaTeX) from the run records only.


rule tables:
    input:
        records=eval_records(),
    output:
        [
            report(f, caption="report/tables.rst", category="Tables")
            for f in table_files()
        ],
    conda:
        "envs/egobench.yaml"
    log:
        f"{R}/logs/tables.log",
    params:
        out_dir=lambda wildcards, output: os.path.dirname(output[0]),
    threads: res("tables", "threads")
    resources:
        mem_mb=res("tables", "mem_mb"),
    shell:
        "egobench tables --records {input.records} --out-dir {params.out_dir} > {log} 2>&1"
