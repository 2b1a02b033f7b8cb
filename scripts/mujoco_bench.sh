#!/usr/bin/env bash
# Run scripts/mujoco_bench.py (MuJoCo's step time on a scene exported by the twin) inside its own
# virtual environment, creating it on first use with the MuJoCo version the script was verified
# with. All arguments go to the script, e.g.
#
#   scripts/mujoco_bench.sh --scene SCENE.json --urdf assets/rover/rover.urdf --seconds 20 --json-out RESULT.json
#
# Environment: ROVER_TWIN_MUJOCO_VENV overrides the environment's place
# (default ~/.cache/rover-twin/mujoco-venv). Quiet when all is well: pip's output goes to a log that
# is shown only if the installation fails. Exit status: the script's (2 when MuJoCo cannot be set up).
set -euo pipefail

MUJOCO_VERSION="4.0.0"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="${ROVER_TWIN_MUJOCO_VENV:-$HOME/.cache/rover-twin/mujoco-venv}"
py="$venv/bin/python"

have_mujoco() {
    [ -x "$py" ] && "$py" -c "import sys, mujoco; sys.exit(mujoco.__version__ != '$MUJOCO_VERSION')" 2>/dev/null
}

if ! have_mujoco; then
    mkdir -p "$(dirname "$venv")"
    log="$(mktemp)"
    echo "mujoco_bench: setting up MuJoCo $MUJOCO_VERSION in $venv (first use)" >&2
    if ! { [ -x "$py" ] || python3 -m venv "$venv"; } >"$log" 2>&1 \
        || ! "$py" -m pip install --disable-pip-version-check --quiet "mujoco==$MUJOCO_VERSION" >>"$log" 2>&1 \
        || ! have_mujoco; then
        cat "$log" >&2
        echo "mujoco_bench: could not install mujoco==$MUJOCO_VERSION into $venv" \
            "(python3 -m venv needs the python3-venv package on Debian/Ubuntu; pip needs network access)" >&2
        rm -f "$log"
        exit 2
    fi
    rm -f "$log"
fi

exec "$py" "$here/mujoco_bench.py" "$@"
