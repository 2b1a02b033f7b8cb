#!/usr/bin/env bash
# Opens a run in Foxglove Studio and saves a screenshot of its 3D panel and head camera, as a user
# would see the run: the last open-source release of Foxglove Studio (@foxglove/studio-base 1.48.0,
# MPL-2.0, the code Lichtblick forked; no registry ships a built Lichtblick), hosted on loopback and
# driven in headless Chromium (Debian's, software WebGL) by Playwright. Prints the problems the
# viewer reports (topics it cannot read) and exits 1 if there are any. Not part of CI: it installs
# about 40 MB from npm into $HOME/.cache/rover-twin/foxglove-view and needs Debian's chromium
# (installed with apt if missing).
# Usage: scripts/foxglove_screenshot.sh RUN_DIR OUT.png
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
run="$(cd "$1" && pwd)/run.mcap"
out="$(cd "$(dirname "$2")" && pwd)/$(basename "$2")"
[ -f "$run" ] || { echo "foxglove_screenshot: no $run" >&2; exit 2; }
if ! command -v "${CHROMIUM:-chromium}" >/dev/null 2>&1; then
  echo "foxglove_screenshot: installing Debian's chromium" >&2
  sudo_cmd=""; [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends chromium
fi
export CHROMIUM="$(command -v "${CHROMIUM:-chromium}")"
app="$HOME/.cache/rover-twin/foxglove-view"
mkdir -p "$app"
# The install is marked complete (installed.json) only once npm has succeeded.
if ! cmp -s "$here/foxglove_view/package.json" "$app/installed.json"; then
  echo "foxglove_screenshot: installing Foxglove Studio 1.48.0 and Playwright from npm into $app" >&2
  rm -f "$app/installed.json"
  cp "$here/foxglove_view/package.json" "$app/"
  (cd "$app" && npm install --silent --no-audit --no-fund >/dev/null)
  cp "$here/foxglove_view/package.json" "$app/installed.json"
fi
cp "$here/foxglove_view/"{index.html,view.js,serve.mjs,shot.mjs} "$app/"
portfile="$(mktemp)"
trap 'kill $server 2>/dev/null || true; rm -f "$portfile"' EXIT
rm -f "$portfile"
node "$app/serve.mjs" "$app" "$run" "$portfile" &
server=$!
for _ in $(seq 100); do [ -s "$portfile" ] && break; sleep 0.1; done
[ -s "$portfile" ] || { echo "foxglove_screenshot: the file server did not start" >&2; exit 2; }
(cd "$app" && node shot.mjs "$(cat "$portfile")" "$run" "$out")
