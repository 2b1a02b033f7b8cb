"""Validates a run's logs with the official readers: the mcap package (Python) iterates the MCAP
with CRC checks, every message whose schema is a Foxglove one (foxglove.Log, foxglove.FrameTransform,
...) is validated against Foxglove's published JSON schema of that name, every message of our own
(rover_twin.*) against the schema its channel gives, which must be one that Foxglove's viewers can
read, and rerun-sdk loads the .rrd. Usage: validate_logs.py RUN_DIR FOXGLOVE_SCHEMA_DIR"""
import json
import sys
from pathlib import Path

import jsonschema
from mcap.reader import make_reader



def foxglove_reads(s, path="message"):
    """Foxglove Studio's and Lichtblick's parseJsonSchema turn a JSON schema into message
    definitions only if every property has one type among these, objects list their properties
    and arrays their items (no arrays of arrays); any other property makes them refuse the topic."""
    t = s.get("type")
    if t in ("boolean", "string", "number", "integer"):
        return
    if t == "object":
        assert isinstance(s.get("properties"), dict), f"{path}: an object without properties"
        for k, v in s["properties"].items():
            foxglove_reads(v, f"{path}.{k}")
        return
    if t == "array":
        assert isinstance(s.get("items"), dict) and s["items"].get("type") != "array", f"{path}: array items {s.get('items')}"
        foxglove_reads(s["items"], f"{path}[]")
        return
    raise AssertionError(f"{path}: type {t!r} is not one Foxglove reads")


def without_nulls(v):
    """The value with its null fields and null array items left out."""
    if isinstance(v, dict):
        return {k: without_nulls(x) for k, x in v.items() if x is not None}
    if isinstance(v, list):
        return [without_nulls(x) for x in v if x is not None]
    return v


run = Path(sys.argv[1])
official = {}
for p in Path(sys.argv[2]).glob("*.json"):
    schema = json.loads(p.read_text())
    official[schema["title"]] = jsonschema.Draft202012Validator(schema)

# MCAP: every message decodes as JSON, log times never go backwards, the summary agrees.
with open(run / "run.mcap", "rb") as f:
    reader = make_reader(f, validate_crcs=True)
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None, "no summary section"
    counts = {}
    last = 0
    foxglove = {}
    frames = {"world"}  # every frame /tf gives a pose
    entity_frames = {}  # scene entity id -> its frame
    images, calibrations = set(), set()
    own = {}  # our own schemas' validators, by schema id
    own_checked = 0
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        assert schema.encoding == "jsonschema", schema.encoding
        value = json.loads(message.data)
        if schema.name.startswith("foxglove."):
            assert schema.name in official, f"{channel.topic}: {schema.name} is no Foxglove schema"
            errors = list(official[schema.name].iter_errors(value))
            assert not errors, f"{channel.topic}: not a valid {schema.name}: {errors[0].message} at {list(errors[0].absolute_path)}"
            foxglove[schema.name] = foxglove.get(schema.name, 0) + 1
            if schema.name == "foxglove.FrameTransform":
                frames.add(value["child_frame_id"])
                if value["child_frame_id"] == "map":
                    assert value["parent_frame_id"] == "world", value
                    foxglove["world -> map transform"] = 1
            if schema.name == "foxglove.SceneUpdate":
                for e in value["entities"]:
                    entity_frames[e["id"]] = e["frame_id"]
            if schema.name == "foxglove.RawImage":
                images.add(channel.topic)
            if schema.name == "foxglove.CameraCalibration":
                calibrations.add(channel.topic)
        else:
            assert schema.name.startswith("rover_twin."), f"{channel.topic}: schema {schema.name}"
            if schema.id not in own:
                s = json.loads(schema.data)
                foxglove_reads(s, schema.name)
                own[schema.id] = jsonschema.Draft202012Validator(s)
            # null stands for an unset value anywhere (Foxglove's subset cannot say "nullable",
            # and Foxglove shows a null field as missing): validated as if absent.
            errors = list(own[schema.id].iter_errors(without_nulls(value)))
            assert not errors, f"{channel.topic}: not a valid {schema.name}: {errors[0].message} at {list(errors[0].absolute_path)}"
            own_checked += 1
        assert message.log_time >= last, f"log time goes backwards on {channel.topic}"
        last = message.log_time
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert sum(counts.values()) == summary.statistics.message_count
    for t in ["/tf", "/events", "/messages", "/world/terrain", "/score", "/scene/world", "/scene/robot", "/scene/tracks/truth"]:
        assert counts.get(t, 0) > 0, f"no messages on {t}"
    # The 3D scene: the terrain, the robot's links and the canister are entities, each in a frame
    # the transforms define (or the 3D panel could not place it).
    assert "terrain" in entity_frames, sorted(entity_frames)[:10]
    assert ("canister" in entity_frames) == ("canister" in frames), "the canister's entity goes with its frame"
    assert any(i.startswith("robot/base_link/") for i in entity_frames), "no robot body in the scene"
    lost = {i: f for i, f in entity_frames.items() if f not in frames}
    assert not lost, f"scene entities in frames no transform gives: {dict(list(lost.items())[:5])}"
    # Every image has the calibrations of its camera beside it (as built, as believed).
    for t in images:
        for c in (f"{t}/calibration", f"{t}/calibration_believed"):
            assert c in calibrations, f"{t}: no {c}"
    assert "world -> map transform" in foxglove, "no world -> map transform: the estimates (frame map) would not show in 3D"
    meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert "rover_twin" in meta and {"scenario", "seed", "version"} <= set(meta["rover_twin"]), meta
print(f"mcap ok: {sum(counts.values())} messages on {len(counts)} topics, metadata {meta['rover_twin']}")
checked = ", ".join(f"{n} {k}" for k, n in sorted(foxglove.items()))
print(f"3d scene ok: {len(entity_frames)} entities, all in the {len(frames)} frames of /tf; {len(images)} image topics with their calibrations")
print(f"foxglove schemas ok: {checked}")
print(f"own schemas ok: {own_checked} messages valid against the {len(own)} rover_twin schemas, all readable by Foxglove")

# Rerun: the recording loads in rerun-sdk, holds the expected entities and a default blueprint.
import rerun.experimental as rrx  # noqa: E402

reader = rrx.RrdReader(str(run / "run.rrd"))
chunks = reader.stream().to_chunks()
paths = {str(c.entity_path) for c in chunks}
for e in ["/world/terrain", "/world/truth/base_link", "/world/estimate/localization_pose", "/logs/events", "/score"]:
    assert e in paths, f"{e} not in the recording ({sorted(paths)[:20]}...)"
assert any(b.kind == "blueprint" for b in reader.blueprints()), "no blueprint in the recording"
print(f"rrd ok: {len(chunks)} chunks, {len(paths)} entities, with a blueprint")
