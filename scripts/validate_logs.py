"""Validates a run's logs with the official readers: the mcap package (Python) iterates the MCAP
with CRC checks, and rerun-sdk loads the .rrd. Usage: validate_logs.py RUN_DIR"""
import json
import sys
from pathlib import Path

from mcap.reader import make_reader

run = Path(sys.argv[1])

# MCAP: every message decodes as JSON, log times never go backwards, the summary agrees.
with open(run / "run.mcap", "rb") as f:
    reader = make_reader(f, validate_crcs=True)
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None, "no summary section"
    counts = {}
    last = 0
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        assert schema.encoding == "jsonschema", schema.encoding
        json.loads(message.data)
        assert message.log_time >= last, f"log time goes backwards on {channel.topic}"
        last = message.log_time
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert sum(counts.values()) == summary.statistics.message_count
    for t in ["/tf", "/events", "/messages", "/world/terrain", "/score"]:
        assert counts.get(t, 0) > 0, f"no messages on {t}"
print(f"mcap ok: {sum(counts.values())} messages on {len(counts)} topics")

# Rerun: the recording loads in rerun-sdk, holds the expected entities and a default blueprint.
import rerun.experimental as rrx  # noqa: E402

reader = rrx.RrdReader(str(run / "run.rrd"))
chunks = reader.stream().to_chunks()
paths = {str(c.entity_path) for c in chunks}
for e in ["/world/terrain", "/world/truth/base_link", "/world/estimate/localization_pose", "/logs/events", "/score"]:
    assert e in paths, f"{e} not in the recording ({sorted(paths)[:20]}...)"
assert any(b.kind == "blueprint" for b in reader.blueprints()), "no blueprint in the recording"
print(f"rrd ok: {len(chunks)} chunks, {len(paths)} entities, with a blueprint")
