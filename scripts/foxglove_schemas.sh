#!/usr/bin/env bash
# Prints a folder holding Foxglove's official JSON schemas, one file a message type (Log.json,
# FrameTransform.json, ...), as the @foxglove/schemas npm package (2.1.0) publishes them: fetched
# with npm pack on first use and written out with Node.js into $HOME/.cache/rover-twin.
# Usage: dir="$(scripts/foxglove_schemas.sh)"
set -euo pipefail
version="2.1.0"
cache="$HOME/.cache/rover-twin/foxglove-schemas-$version"
if [ ! -f "$cache/.complete" ]; then
  echo "foxglove_schemas: fetching @foxglove/schemas@$version from npm" >&2
  tmp="$(mktemp -d)"
  trap 'rm -rf "$tmp"' EXIT
  (cd "$tmp" && npm pack --silent "@foxglove/schemas@$version" >/dev/null)
  tar -xzf "$tmp/foxglove-schemas-$version.tgz" -C "$tmp"
  mkdir -p "$cache"
  node -e '
    const schemas = require(process.argv[1]);
    const fs = require("fs");
    for (const [name, schema] of Object.entries(schemas)) {
      fs.writeFileSync(`${process.argv[2]}/${name}.json`, JSON.stringify(schema));
    }' "$tmp/package/dist/jsonschema/index.js" "$cache"
  touch "$cache/.complete"
fi
echo "$cache"
