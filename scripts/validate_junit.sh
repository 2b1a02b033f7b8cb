#!/usr/bin/env bash
# Validates a sweep's junit.xml against the JUnit XML schema CI systems read (Surefire's
# junit-10.xsd, as pytest ships it for its own JUnit tests: taken from the pytest 9.2.0 source
# distribution on PyPI, checked by its SHA-256) with the Python xmlschema package. Both are cached
# in $HOME/.cache/rover-twin (the virtual environment is the one validate_logs.sh uses).
# Usage: scripts/validate_junit.sh JUNIT_XML
set -euo pipefail
cache="$HOME/.cache/rover-twin"
venv="${ROVER_TWIN_VENV:-$cache/venv}"
xsd="$cache/junit-10.xsd"
xsd_sha256="a1a816f58d1bf95ebabf371994df0b9246dee66ea9572fbec4f9296f1b2c0ff6"
mkdir -p "$cache"
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
fi
if ! "$venv/bin/python" -c "import xmlschema; assert xmlschema.__version__ == '4.3.2'" 2>/dev/null; then
  echo "validate_junit: installing xmlschema==4.3.2 into $venv"
  "$venv/bin/pip" install -q --disable-pip-version-check xmlschema==4.3.2
fi
if [ ! -f "$xsd" ] || ! echo "$xsd_sha256  $xsd" | sha256sum -c --quiet - 2>/dev/null; then
  echo "validate_junit: fetching junit-10.xsd from the pytest 9.2.0 source distribution"
  tmp="$(mktemp -d)"
  trap 'rm -rf "$tmp"' EXIT
  "$venv/bin/pip" download -q --disable-pip-version-check --no-deps --no-binary :all: -d "$tmp" pytest==9.2.0
  tar -xzf "$tmp"/pytest-9.2.0.tar.gz -C "$tmp" pytest-9.2.0/testing/example_scripts/junit-10.xsd
  echo "$xsd_sha256  $tmp/pytest-9.2.0/testing/example_scripts/junit-10.xsd" | sha256sum -c --quiet -
  cp "$tmp/pytest-9.2.0/testing/example_scripts/junit-10.xsd" "$xsd"
fi
"$venv/bin/python" - "$xsd" "$1" <<'PY'
import sys
import xml.etree.ElementTree as ET
import xmlschema

schema = xmlschema.XMLSchema(sys.argv[1])
schema.validate(sys.argv[2])
root = ET.parse(sys.argv[2]).getroot()
cases = root.findall(".//testcase")
failed = [c for c in cases if c.find("failure") is not None or c.find("error") is not None]
print(f"validate_junit: {sys.argv[2]} is valid JUnit XML: {len(cases)} test cases ({len(cases) - len(failed)} passed, {len(failed)} recorded as failure or error)")
PY
