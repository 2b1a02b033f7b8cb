#!/usr/bin/env bash
# Checks a run's Rerun and MCAP files with the official Python readers at the pinned versions
# (mcap 1.6.0, rerun-sdk 0.36.3 = the rerun crate's version), and every Foxglove-schema message of
# the MCAP against Foxglove's published JSON schemas (@foxglove/schemas 2.1.0, jsonschema 4.26.0). The virtual environment lives in
# $HOME/.cache/rover-twin/venv so that CI reuses it; nothing depends on it being there.
# Usage: scripts/validate_logs.sh RUN_DIR
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="${ROVER_TWIN_VENV:-$HOME/.cache/rover-twin/venv}"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import mcap, rerun, jsonschema; assert rerun.__version__ == '0.36.3'" 2>/dev/null; then
  echo "validate_logs: installing mcap==1.6.0 rerun-sdk==0.36.3 jsonschema==4.26.0 into $venv"
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q --disable-pip-version-check mcap==1.6.0 rerun-sdk==0.36.3 jsonschema==4.26.0
fi
"$venv/bin/python" "$here/validate_logs.py" "$1" "$("$here/foxglove_schemas.sh")"
"$venv/bin/rerun" rrd verify "$1/run.rrd"
