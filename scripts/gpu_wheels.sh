#!/usr/bin/env bash
# The wheels scripts/gpu_check.sh installs on the device machine, whose image (Python 3.12, torch
# 2.11+cu130, numpy, numba, pandas, ... see the device tool's KINDS.md) lacks these: gsplat, snakemake
# and its dependencies, jsonschema, plyfile. Pure-Python ones build anywhere; the compiled ones
# (greenlet, immutables, pydantic_core, rpds_py, sqlalchemy) are fetched for CPython 3.12 / x86-64.
#   usage: bash scripts/gpu_wheels.sh [DIR=.whl]        (then carry DIR in the device call)
set -euo pipefail
DIR=${1:-.whl}
PURE="annotated_types==0.8.0 argparse_dataclass==2.0.0 conda_inject==1.3.2 configargparse==1.9.0
connection_pool==0.0.3 docutils==0.22.4 dpath==2.2.0 fastjsonschema==2.22.3 gitdb==4.0.12 gitpython==3.2.1
gsplat==1.5.3 humanfriendly==10.0 jsonschema==4.26.0 jsonschema_specifications==2025.9.1 jupyter_core==5.9.1
nbformat==5.11.1 platformdirs==4.14.8 plyfile==1.1.5 pulp==3.3.2 pydantic==2.14.4 referencing==0.37.0
smart_open==7.7.1 smmap==5.0.3 snakemake==9.27.1 snakemake_interface_common==1.23.0
snakemake_interface_executor_plugins==9.4.0 snakemake_interface_logger_plugins==2.1.0
snakemake_interface_report_plugins==1.3.0 snakemake_interface_scheduler_plugins==2.0.2
snakemake_interface_storage_plugins==4.4.1 sqlmodel==0.0.37 tenacity==9.2.1 throttler==1.2.3 traitlets==5.16.1
typing_inspection==0.4.5 yte==1.9.4"
BINARY="greenlet==3.5.6 immutables==0.21 pydantic_core==2.50.5 rpds_py==2026.9.1 sqlalchemy==2.0.58"
mkdir -p "$DIR"
# shellcheck disable=SC2086
python3 -m pip wheel -q --no-deps -w "$DIR" $PURE
# shellcheck disable=SC2086
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 -d "$DIR" $BINARY
ls "$DIR" | wc -l
