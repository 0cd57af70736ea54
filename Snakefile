# pointmark workflow: catalogue -> sharded embedding.  Logic lives behind the CLI.
#   snakemake --cores 2 --configfile configs/workflow.yaml
from snakemake.utils import min_version, validate

min_version("8.0")


configfile: "configs/workflow.yaml"


validate(config, "configs/schema.json")

CONFIG = workflow.configfiles[-1]
WF = config["workflow"]
SHARDS = range(WF["shards"])
RECIPIENTS = ",".join(config["recipients"])


rule all:
    input:
        expand(f"{WF['stamps']}/embed-{{shard}}-of-{WF['shards']}.done", shard=SHARDS),


rule catalogue:
    input:
        WF["assets"],
    output:
        WF["catalogue"],
    log:
        f"{WF['stamps']}/catalogue.log",
    params:
        recipients=RECIPIENTS,
    conda:
        "envs/pointmark.yaml"
    shell:
        "pointmark catalog build {input} --out {output} --recipients {params.recipients} > {log} 2>&1"


rule embed:
    input:
        catalogue=WF["catalogue"],
        config=CONFIG,
    output:
        touch(f"{WF['stamps']}/embed-{{shard}}-of-{WF['shards']}.done"),
    log:
        f"{WF['stamps']}/embed-{{shard}}-of-{WF['shards']}.log",
    params:
        shard=lambda wildcards: f"{wildcards.shard}/{WF['shards']}",
    conda:
        "envs/pointmark.yaml"
    shell:
        "pointmark run {input.config} --shard {params.shard} "
        "--set catalog.source={input.catalogue} > {log} 2>&1"


# Scheduled leak scan: `snakemake --cores 2 --forcerun scan scan` (see README for cron).
# pointmark scan exits 1 when it found a match; that is a result, not a failure.
rule scan:
    input:
        catalogue=WF["catalogue"],
        config=CONFIG,
        embedded=expand(f"{WF['stamps']}/embed-{{shard}}-of-{WF['shards']}.done", shard=SHARDS),
    output:
        touch(f"{WF['stamps']}/scan.done"),
    log:
        f"{WF['stamps']}/scan.log",
    conda:
        "envs/pointmark.yaml"
    shell:
        "pointmark scan {input.config} --set scan.catalogue={input.catalogue} > {log} 2>&1 "
        "|| [ $? -eq 1 ]"


# Robustness report (heavy, on demand): `snakemake --cores 2 evaluate`.
rule evaluate:
    input:
        config=CONFIG,
    output:
        f"{config['evaluate']['out']}/summary.md",
    log:
        f"{WF['stamps']}/evaluate.log",
    conda:
        "envs/pointmark.yaml"
    shell:
        "pointmark evaluate {input.config} > {log} 2>&1"
