#!/usr/bin/env python3
"""Write a synthetic SCENE.json for scripts/mujoco_bench.py (for testing the benchmark on its own).

The scene has the shape the Rust side exports from a real world: a 257 x 257 heightfield at
0.15625 m per cell (40 m x 40 m) of gentle noise (a few centimetres), 60 fixed rocks given as point
clouds of 8 to 12 points (0.1 m to 0.4 m across) whose convex hulls are the rocks, and the rover
starting at the centre, driving straight along +x. Deterministic for a given --seed. Standard
library only (no numpy, no MuJoCo), so it runs with any python3.

    python3 scripts/mujoco_bench_scene_example.py --out /tmp/scene.json [--seed 7]
"""

import argparse
import json
import math
import random
import sys

# The rover's geometry (assets/rover/rover.urdf): base_link sits 0.22 m above the wheel centres
# (rocker -0.10, wheel -0.12) and the wheels have a radius of 0.16 m.
BASE_ABOVE_GROUND_M = 0.22 + 0.16

WHEEL_JOINTS = [
    "wheel_front_left_joint",
    "wheel_front_right_joint",
    "wheel_rear_left_joint",
    "wheel_rear_right_joint",
]
HELD_JOINTS = [
    "arm_joint_1",
    "arm_joint_2",
    "arm_joint_3",
    "arm_joint_4",
    "arm_joint_5",
    "arm_joint_6",
    "ptu_pan_joint",
    "ptu_tilt_joint",
    "gripper_finger_left_joint",
    "gripper_finger_right_joint",
]


def make_height_function(rng):
    """A smooth random surface: a sum of a few random plane waves, amplitude about 3 cm in all."""
    waves = []
    for k in range(6):
        wavelength = rng.uniform(2.0, 12.0)  # m
        direction = rng.uniform(0.0, 2.0 * math.pi)
        amplitude = rng.uniform(0.004, 0.010)  # m; six of them: a few cm peak to peak
        phase = rng.uniform(0.0, 2.0 * math.pi)
        kx = 2.0 * math.pi / wavelength * math.cos(direction)
        ky = 2.0 * math.pi / wavelength * math.sin(direction)
        waves.append((kx, ky, amplitude, phase))

    def height(x, y):
        return sum(a * math.sin(kx * x + ky * y + p) for kx, ky, a, p in waves)

    return height


def make_rock(rng, size_m):
    """8 to 12 points roughly on an ellipsoid of the given size, partly buried (local frame, z up)."""
    n = rng.randint(8, 12)
    half = size_m / 2.0
    sx, sy, sz = half, half * rng.uniform(0.6, 1.0), half * rng.uniform(0.4, 0.8)
    points = []
    for _ in range(n):
        # A random direction, scaled into the ellipsoid with some roughness.
        u, v = rng.uniform(-1.0, 1.0), rng.uniform(0.0, 2.0 * math.pi)
        r = math.sqrt(1.0 - u * u)
        s = rng.uniform(0.8, 1.0)
        points.append([s * sx * r * math.cos(v), s * sy * r * math.sin(v), s * sz * u])
    # Sink the rock by a third of its height so it sits in the ground rather than on it.
    sink = sz / 3.0
    return [[round(p[0], 5), round(p[1], 5), round(p[2] - sink, 5)] for p in points]


def make_scene(seed, nx=257, ny=257, cell_m=0.15625, n_rocks=60):
    rng = random.Random(seed)
    height = make_height_function(rng)
    # Centre the field on the world origin.
    x0 = -(nx - 1) * cell_m / 2.0
    y0 = -(ny - 1) * cell_m / 2.0
    heights = []
    for j in range(ny):  # row j: y = y0 + j * cell_m
        y = y0 + j * cell_m
        for i in range(nx):  # column i: x = x0 + i * cell_m
            heights.append(round(height(x0 + i * cell_m, y), 5))

    start = {"x": 0.0, "y": 0.0, "yaw": 0.0}
    start["base_z"] = round(height(start["x"], start["y"]) + BASE_ABOVE_GROUND_M + 0.02, 5)

    rocks = []
    span_x, span_y = (nx - 1) * cell_m, (ny - 1) * cell_m
    while len(rocks) < n_rocks:
        x = x0 + rng.uniform(0.5, span_x - 0.5)
        y = y0 + rng.uniform(0.5, span_y - 0.5)
        if math.hypot(x - start["x"], y - start["y"]) < 2.0:
            continue  # keep the start clear so the rover does not spawn inside a rock
        rocks.append(
            {
                "position": [round(x, 4), round(y, 4), round(height(x, y), 4)],
                "yaw": round(rng.uniform(-math.pi, math.pi), 4),
                "points": make_rock(rng, rng.uniform(0.1, 0.4)),
            }
        )

    return {
        "heightfield": {"nx": nx, "ny": ny, "cell_m": cell_m, "origin": [x0, y0], "heights": heights},
        "rocks": rocks,
        "start": start,
        "dt_s": 0.005,
        "substeps": 4,
        "gravity_m_s2": 9.81,
        "wheel_joints": WHEEL_JOINTS,
        "wheel_rate_rad_s": 1.2,
        "held_joints": HELD_JOINTS,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="where to write SCENE.json")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    scene = make_scene(args.seed)
    with open(args.out, "w") as f:
        json.dump(scene, f, separators=(",", ":"))
    print(f"wrote {args.out}: {scene['heightfield']['nx']}x{scene['heightfield']['ny']} heightfield, "
          f"{len(scene['rocks'])} rocks", file=sys.stderr)


if __name__ == "__main__":
    main()
