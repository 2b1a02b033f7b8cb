#!/usr/bin/env bash
# Enforces the dependency direction of ARCHITECTURE.md:
#   framework depends on no crate of ours; gnc never on twin, rapier, parry or wgpu (it sees the world
#   only through the framework's HAL); twin and gnc never on each other; worlds on none of ours but
#   framework; logger on framework and worlds only (no twin, gnc or scenarios: it is told what to
#   draw through its run header); net on framework only, and no module crate on net (a module does
#   not know whether it runs local or remote)... and nothing depends on scenarios.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
fail=0
deps() { cargo tree --locked -p "$1" -e normal --prefix none --format '{p}' 2>/dev/null | awk '{print $1}' | sort -u; }
forbid() { # crate, forbidden dependency names...
  local crate=$1; shift
  local have; have=$(deps "$crate")
  for f in "$@"; do
    if grep -qx "$f" <<<"$have"; then
      echo "layering: '$crate' must not depend on '$f'" >&2
      fail=1
    fi
  done
}
forbid framework twin gnc worlds logger net scenarios
forbid gnc twin worlds net scenarios rapier3d parry3d wgpu
forbid twin gnc net scenarios
forbid net twin gnc worlds logger scenarios rapier3d wgpu
forbid worlds twin gnc scenarios rapier3d wgpu
forbid logger twin gnc scenarios rapier3d wgpu
[ $fail -eq 0 ] && echo "layering: ok"
exit $fail
