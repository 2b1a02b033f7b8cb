#!/usr/bin/env python3
"""MuJoCo reference benchmark: the wall time of one physics step of our rover on a given terrain.

Why: the twin simulates the rover with rapier3d (crate `twin`). A user choosing a simulator would
weigh it against MuJoCo, the usual engine for articulated robots. This script builds the *same*
scene in MuJoCo -- the rover from its URDF, the terrain heightfield, the rocks as convex hulls, the
wheels driven by force-limited velocity motors, the arm / pan-tilt / gripper joints held by position
servos, the rockers passive and sprung -- drives the rover straight, and measures the mean wall time
of `mujoco.mj_step`. The Rust side exports its scene to SCENE.json and calls this script, so both
engines are timed on one machine in one run:

    python3 scripts/mujoco_bench.py --scene SCENE.json --urdf assets/rover/rover.urdf --seconds 20 \
        [--json-out RESULT.json]

(`scripts/mujoco_bench.sh` does the same inside a virtual environment that has MuJoCo.)

What is measured: after 1 s of settling (wheels held at rest), `--seconds` of simulated time are
stepped with the wheels at the commanded rate, in chunks of `mj_step(m, d, nstep)`; only those calls
are inside the `time.perf_counter` intervals, so Python's per-step overhead is not counted and the
bookkeeping between chunks (tilt, contact counts) is not timed. The result is the mean wall time
per step in microseconds, with MuJoCo's version, the model's size, the contacts at the end, the
distance the rover drove (a sanity check: about wheel_rate x wheel_radius x seconds on gentle
ground) and whether it stayed upright.

Equivalence with the twin, and where it stops:
- One MuJoCo step is one twin step: MuJoCo's timestep is the scene's dt_s. MuJoCo has no substeps
  (its implicit integrator and Newton solver need none at 5 ms); the scene's `substeps` (rapier's
  substeps per step) is only echoed in the output.
- Integrator `implicitfast` (MuJoCo's recommendation for stiff actuators), Newton solver, pyramidal
  friction cones, default solver tolerances and contact softness: MuJoCo as a user would run it.
- Gains come from the twin's configuration (`twin.toml` beside the URDF, when present): wheel
  velocity gain and torque limit, rocker spring and damper, servo stiffness (full effort at
  `full_effort_error`, x 0.1 in metres for prismatic joints) and damping (`damping_time_s`).
  Effort limits come from the URDF. Contact friction is `--friction` (0.8) on every geom.
- The URDF's root link is a floating base: a free joint is inserted above it (MuJoCo would weld the
  root link to the world otherwise), so its pose is the scene's start pose.

Exit status: 0 measured, 2 bad input or MuJoCo missing, 1 anything else.
"""

import argparse
import json
import math
import os
import sys
import time
import xml.etree.ElementTree as ET

VENV = os.path.join(os.path.expanduser("~"), ".cache", "rover-twin", "mujoco-venv")

try:
    import mujoco
    import numpy as np
except ImportError as e:  # MuJoCo lives in its own virtual environment, not in the system Python.
    print(
        f"mujoco_bench: cannot import MuJoCo ({e}).\n"
        f"  Run scripts/mujoco_bench.sh (it creates the environment and passes its arguments on), or:\n"
        f"    python3 -m venv {VENV} && {VENV}/bin/pip install mujoco==4.0.0\n"
        f"  then run this script with {VENV}/bin/python.",
        file=sys.stderr,
    )
    sys.exit(2)

# Free joint inserted above the URDF's root link (see load_rover).
FREE_JOINT = "floating_base"
# Twin parameters used when no twin.toml is found (the values of assets/rover/twin.toml).
TWIN_DEFAULTS = {
    "wheel_kv": 400.0,  # [wheels] velocity_gain, N m per rad/s
    "wheel_max_torque": 40.0,  # [wheels] max_torque_nm
    "rocker_stiffness": 3000.0,  # [suspension] stiffness, N m/rad
    "rocker_damping": 300.0,  # [suspension] damping, N m s/rad
    "servo_full_effort_error": 0.04,  # [servos] full_effort_error, rad (x 0.1 m for prismatic)
    "servo_damping_time": 0.06,  # [servos] damping_time_s
}
SETTLE_S = 1.0
CHUNK_S = 0.1  # simulated time per timed mj_step(m, d, nstep) call
UPRIGHT_MAX_TILT_DEG = 45.0


class BadInput(Exception):
    """The scene, the URDF or an option is unusable (exit status 2)."""


# ---------------------------------------------------------------------------------------------
# Inputs


def load_scene(path):
    """Read SCENE.json and check the fields this script uses."""
    try:
        with open(path) as f:
            scene = json.load(f)
    except (OSError, ValueError) as e:
        raise BadInput(f"{path}: {e}")
    try:
        hf = scene["heightfield"]
        nx, ny, cell = int(hf["nx"]), int(hf["ny"]), float(hf["cell_m"])
        heights = np.asarray(hf["heights"], dtype=np.float64).ravel()
        if nx < 2 or ny < 2 or cell <= 0.0:
            raise BadInput(f"{path}: heightfield needs nx, ny >= 2 and cell_m > 0")
        if heights.size != nx * ny:
            raise BadInput(f"{path}: heightfield has {heights.size} heights, nx*ny = {nx * ny}")
        if not np.all(np.isfinite(heights)):
            raise BadInput(f"{path}: heightfield has non-finite heights")
        hf["heights"] = heights.reshape(ny, nx)  # row j: y, column i: x
        for k in ("x", "y", "yaw", "base_z"):
            float(scene["start"][k])
        for k in ("dt_s", "gravity_m_s2", "wheel_rate_rad_s"):
            float(scene[k])
        if float(scene["dt_s"]) <= 0.0:
            raise BadInput(f"{path}: dt_s must be positive")
        for n, rock in enumerate(scene["rocks"]):
            pts = np.asarray(rock["points"], dtype=np.float64)
            if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 4:
                raise BadInput(f"{path}: rock {n} needs at least 4 points [x, y, z]")
            float(rock["yaw"]), [float(v) for v in rock["position"]]
        list(scene["wheel_joints"]), list(scene["held_joints"])
    except (KeyError, TypeError, ValueError) as e:
        raise BadInput(f"{path}: not a benchmark scene ({type(e).__name__}: {e})")
    return scene


def load_twin_params(path):
    """The twin's actuator and suspension parameters, from its twin.toml when there is one."""
    params = dict(TWIN_DEFAULTS)
    if path is None:
        return params, "built-in defaults (assets/rover/twin.toml values)"
    try:
        import tomllib  # Python >= 3.11
    except ImportError:
        return params, "built-in defaults (no tomllib in this Python)"
    try:
        with open(path, "rb") as f:
            cfg = tomllib.load(f)
    except (OSError, ValueError) as e:
        raise BadInput(f"{path}: {e}")
    wheels, susp, servos = cfg.get("wheels", {}), cfg.get("suspension", {}), cfg.get("servos", {})
    params["wheel_kv"] = float(wheels.get("velocity_gain", params["wheel_kv"]))
    params["wheel_max_torque"] = float(wheels.get("max_torque_nm", params["wheel_max_torque"]))
    params["rocker_stiffness"] = float(susp.get("stiffness", params["rocker_stiffness"]))
    params["rocker_damping"] = float(susp.get("damping", params["rocker_damping"]))
    params["servo_full_effort_error"] = float(
        servos.get("full_effort_error", params["servo_full_effort_error"]))
    params["servo_damping_time"] = float(servos.get("damping_time_s", params["servo_damping_time"]))
    return params, path


# ---------------------------------------------------------------------------------------------
# Model


def load_rover(urdf_path):
    """The rover as an MjSpec, with a free joint above its root link.

    MuJoCo turns a URDF's root link into the world body (the robot would be welded to the ground
    and the root link's mass dropped). So the URDF is rewritten in memory: a massless link is added
    as the new root with a `floating` joint (MuJoCo: free joint) to the old root, which becomes an
    ordinary body with its inertia. A `<mujoco><compiler>` element discards the visual geometry
    and resolves any mesh files relative to the URDF's directory.
    """
    try:
        tree = ET.parse(urdf_path)
    except (OSError, ET.ParseError) as e:
        raise BadInput(f"{urdf_path}: {e}")
    robot = tree.getroot()
    links = [l.get("name") for l in robot.findall("link")]
    children = {j.find("child").get("link") for j in robot.findall("joint")}
    roots = [l for l in links if l not in children]
    if len(roots) != 1:
        raise BadInput(f"{urdf_path}: expected one root link, found {roots}")
    root = roots[0]

    urdf_dir = os.path.dirname(os.path.abspath(urdf_path))
    mj = ET.SubElement(robot, "mujoco")
    ET.SubElement(mj, "compiler", discardvisual="true", meshdir=urdf_dir, strippath="false")
    ET.SubElement(robot, "link", name="mujoco_world")
    joint = ET.SubElement(robot, "joint", name=FREE_JOINT, type="floating")
    ET.SubElement(joint, "parent", link="mujoco_world")
    ET.SubElement(joint, "child", link=root)
    try:
        spec = mujoco.MjSpec.from_string(ET.tostring(robot, encoding="unicode"))
    except Exception as e:  # mujoco raises ValueError with the parser's message
        raise BadInput(f"{urdf_path}: MuJoCo cannot load it: {e}")
    return spec, root


def add_terrain(spec, hf):
    """The heightfield as an hfield geom: MuJoCo wants data in [0, 1], scaled by size[2].

    MuJoCo's hfield spans [-size[0], size[0]] x [-size[1], size[1]] around its geom, with data row 0
    at -y and column 0 at -x (checked with mj_ray), the same layout as the scene's; size[3] is the
    depth of the solid base below the lowest point.
    """
    H = hf["heights"]
    ny, nx = H.shape
    cell = float(hf["cell_m"])
    x0, y0 = (float(v) for v in hf["origin"])
    hmin, hmax = float(H.min()), float(H.max())
    span = max(hmax - hmin, 1e-6)  # a flat field still needs a positive elevation scale
    rx, ry = (nx - 1) * cell / 2.0, (ny - 1) * cell / 2.0
    spec.add_hfield(
        name="terrain",
        size=[rx, ry, span, 1.0],
        nrow=ny,
        ncol=nx,
        userdata=((H - hmin) / span).ravel().tolist(),
    )
    spec.worldbody.add_geom(
        name="terrain",
        type=mujoco.mjtGeom.mjGEOM_HFIELD,
        hfieldname="terrain",
        pos=[x0 + rx, y0 + ry, hmin],
    )


def yaw_quat(yaw):
    """Quaternion (w, x, y, z) of a rotation about z."""
    return [math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)]


def add_rocks(spec, rocks):
    """Each rock: a mesh from its points (MuJoCo collides with the convex hull), fixed in the world."""
    for n, rock in enumerate(rocks):
        name = f"rock_{n}"
        spec.add_mesh(name=name, uservert=np.asarray(rock["points"], dtype=np.float64).ravel().tolist())
        spec.worldbody.add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=name,
            pos=[float(v) for v in rock["position"]],
            quat=yaw_quat(float(rock["yaw"])),
        )


def find_joint(spec, name, role):
    j = spec.joint(name)
    if j is None:
        names = sorted(jj.name for jj in spec.joints if jj.name and jj.name != FREE_JOINT)
        raise BadInput(f"scene {role} '{name}' is not a joint of the URDF (joints: {', '.join(names)})")
    return j


def set_coefficient(joint, attr, value):
    """Set a joint's linear spring or damper coefficient.

    MuJoCo 4 made these polynomials ([linear, quadratic, cubic]); older versions take a scalar.
    """
    current = getattr(joint, attr)
    if np.ndim(current) == 0:
        setattr(joint, attr, value)
    else:
        setattr(joint, attr, [value] + [0.0] * (len(current) - 1))


def add_actuators(spec, scene, params):
    """Velocity motors on the wheels, position servos on the held joints, springs on the rockers.

    Returns a description of what was set up, for the report.
    """
    wheels = list(scene["wheel_joints"])
    held = list(scene["held_joints"])
    both = set(wheels) & set(held)
    if both:
        raise BadInput(f"scene: joints both driven and held: {sorted(both)}")

    for name in wheels:
        j = find_joint(spec, name, "wheel joint")
        torque = params["wheel_max_torque"]
        if j.actfrclimited and j.actfrcrange[1] > 0.0:
            torque = min(torque, float(j.actfrcrange[1]))  # the URDF's effort limit
        act = spec.add_actuator(name=f"{name}_vel", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_velocity(kv=params["wheel_kv"])
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-torque, torque]

    servo_gains = {}
    for name in held:
        j = find_joint(spec, name, "held joint")
        effort = float(j.actfrcrange[1]) if j.actfrclimited else 0.0
        if effort <= 0.0:
            raise BadInput(f"URDF joint '{name}' has no effort limit to size its servo from")
        # The twin's servos give their full effort at full_effort_error (rad; x 0.1 in metres for a
        # prismatic joint) and damp with stiffness x damping_time_s.
        err = params["servo_full_effort_error"]
        if j.type == mujoco.mjtJoint.mjJNT_SLIDE:
            err *= 0.1
        kp = effort / err
        kv = kp * params["servo_damping_time"]
        act = spec.add_actuator(name=f"{name}_pos", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=kp, kv=kv)
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-effort, effort]
        servo_gains[name] = {"kp": round(kp, 3), "kv": round(kv, 3), "effort": effort}

    # Hinge joints neither driven nor held are the passive rockers: sprung towards level like the
    # twin's ([suspension]). Other passive joints (none in our URDF) are left free.
    sprung = []
    for j in spec.joints:
        if j.name in (FREE_JOINT, *wheels, *held) or j.type != mujoco.mjtJoint.mjJNT_HINGE:
            continue
        set_coefficient(j, "stiffness", params["rocker_stiffness"])
        set_coefficient(j, "damping", params["rocker_damping"])
        sprung.append(j.name)
    return {"wheels": wheels, "held": held, "sprung": sprung, "servo_gains": servo_gains}


def build_model(scene, urdf_path, params, friction):
    spec, root = load_rover(urdf_path)
    opt = spec.option
    opt.timestep = float(scene["dt_s"])
    opt.gravity = [0.0, 0.0, -float(scene["gravity_m_s2"])]
    opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    add_terrain(spec, scene["heightfield"])
    add_rocks(spec, scene["rocks"])
    setup = add_actuators(spec, scene, params)
    for g in spec.geoms:  # sliding friction on every geom; MuJoCo uses the larger of a pair's
        g.friction = [friction, g.friction[1], g.friction[2]]
    try:
        model = spec.compile()
    except Exception as e:
        raise BadInput(f"MuJoCo cannot compile the scene: {e}")
    return model, root, setup


# ---------------------------------------------------------------------------------------------
# Run


def wheel_radius(model, wheel_joints):
    """Mean radius of the wheels' cylinders (the wheel joints' child bodies), for the sanity check."""
    round_types = {int(t) for t in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_SPHERE,
                                     mujoco.mjtGeom.mjGEOM_CAPSULE)}
    radii = []
    for name in wheel_joints:
        body = model.jnt_bodyid[model.joint(name).id]
        for g in range(model.ngeom):
            if model.geom_bodyid[g] == body and int(model.geom_type[g]) in round_types:
                radii.append(float(model.geom_size[g][0]))
                break
    return sum(radii) / len(radii) if radii else float("nan")


def tilt_deg(data, body):
    """Angle between the body's z axis and the world's, degrees."""
    zz = float(data.xmat[body][8])  # R[2][2]: world-z component of the body's z axis
    return math.degrees(math.acos(max(-1.0, min(1.0, zz))))


def run(scene, urdf_path, seconds, friction, twin_cfg):
    params, params_source = load_twin_params(twin_cfg)
    model, root, setup = build_model(scene, urdf_path, params, friction)
    data = mujoco.MjData(model)

    # Start pose of the root link (the free joint's body frame is the root link's frame).
    st = scene["start"]
    adr = model.jnt_qposadr[model.joint(FREE_JOINT).id]
    data.qpos[adr:adr + 3] = [float(st["x"]), float(st["y"]), float(st["base_z"])]
    data.qpos[adr + 3:adr + 7] = yaw_quat(float(st["yaw"]))
    base = model.body(root).id
    wheel_acts = [model.actuator(f"{n}_vel").id for n in setup["wheels"]]
    held_acts = [model.actuator(f"{n}_pos").id for n in setup["held"]]
    data.ctrl[held_acts] = 0.0  # servos hold 0
    mujoco.mj_forward(model, data)

    dt = model.opt.timestep
    # Settle with the wheels held at rest.
    data.ctrl[wheel_acts] = 0.0
    mujoco.mj_step(model, data, nstep=max(1, round(SETTLE_S / dt)))
    settled_tilt = tilt_deg(data, base)

    # Drive straight and time the steps.
    data.ctrl[wheel_acts] = float(scene["wheel_rate_rad_s"])
    steps_total = max(1, round(seconds / dt))
    chunk = max(1, round(CHUNK_S / dt))
    start_xy = data.xpos[base][:2].copy()
    path_length = 0.0
    last_xy = start_xy.copy()
    wall = 0.0
    chunk_us = []
    max_tilt = settled_tilt
    contacts = []
    done = 0
    while done < steps_total:
        n = min(chunk, steps_total - done)
        t0 = time.perf_counter()
        mujoco.mj_step(model, data, nstep=n)
        dtw = time.perf_counter() - t0
        wall += dtw
        chunk_us.append(dtw / n * 1e6)
        done += n
        # Bookkeeping, not timed.
        xy = data.xpos[base][:2]
        path_length += float(np.linalg.norm(xy - last_xy))
        last_xy = xy.copy()
        max_tilt = max(max_tilt, tilt_deg(data, base))
        contacts.append(int(data.ncon))

    sim_s = steps_total * dt
    radius = wheel_radius(model, setup["wheels"])
    expected = float(scene["wheel_rate_rad_s"]) * radius * sim_s
    displacement = float(np.linalg.norm(data.xpos[base][:2] - start_xy))
    final_tilt = tilt_deg(data, base)
    warnings = {
        mujoco.mjtWarning(i).name: int(data.warning[i].number)
        for i in range(len(data.warning))
        if data.warning[i].number > 0
    }
    finite = bool(np.all(np.isfinite(data.qpos)))
    return {
        "engine": "mujoco",
        "mujoco_version": mujoco.__version__,
        "mean_step_us": wall / steps_total * 1e6,
        "median_chunk_step_us": float(np.median(chunk_us)),
        "min_chunk_step_us": float(min(chunk_us)),
        "max_chunk_step_us": float(max(chunk_us)),
        "steps": steps_total,
        "wall_s": wall,
        "sim_s": sim_s,
        "real_time_factor": sim_s / wall if wall > 0 else float("inf"),
        "dt_s": dt,
        "scene_substeps": int(scene.get("substeps", 1)),
        "substeps_note": "MuJoCo steps once per dt_s (no substeps); scene_substeps is rapier's, for information",
        "integrator": "implicitfast",
        "solver": "Newton",
        "friction": friction,
        "model": {
            "bodies": int(model.nbody),
            "geoms": int(model.ngeom),
            "joints": int(model.njnt),
            "dofs": int(model.nv),
            "actuators": int(model.nu),
            "rocks": len(scene["rocks"]),
            "heightfield": [int(model.hfield_ncol[0]), int(model.hfield_nrow[0])],
        },
        "contacts_end": int(data.ncon),
        "contacts_mean": float(np.mean(contacts)),
        "wheel_radius_m": radius,
        "wheel_rate_rad_s": float(scene["wheel_rate_rad_s"]),
        "displacement_m": displacement,
        "path_length_m": path_length,
        "expected_distance_m": expected,
        "distance_ratio": displacement / expected if expected > 0 else float("nan"),
        "settled_tilt_deg": settled_tilt,
        "max_tilt_deg": max_tilt,
        "final_tilt_deg": final_tilt,
        "upright": finite and max_tilt < UPRIGHT_MAX_TILT_DEG,
        "state_finite": finite,
        "mujoco_warnings": warnings,
        "actuation": {
            "wheels": setup["wheels"],
            "wheel_kv": params["wheel_kv"],
            "wheel_max_torque_nm": params["wheel_max_torque"],
            "held": setup["held"],
            "servo_gains": setup["servo_gains"],
            "sprung_passive_joints": setup["sprung"],
            "rocker_stiffness": params["rocker_stiffness"],
            "rocker_damping": params["rocker_damping"],
            "params_from": params_source,
        },
        "free_joint": FREE_JOINT,
        "root_link": root,
    }


def report(r):
    m = r["model"]
    lines = [
        f"MuJoCo {r['mujoco_version']} step benchmark",
        f"  mean step          {r['mean_step_us']:.1f} us  (median chunk {r['median_chunk_step_us']:.1f}, "
        f"min {r['min_chunk_step_us']:.1f}, max {r['max_chunk_step_us']:.1f})",
        f"  steps              {r['steps']} x {r['dt_s'] * 1e3:g} ms = {r['sim_s']:g} s simulated in "
        f"{r['wall_s']:.3f} s wall ({r['real_time_factor']:.0f}x real time)",
        f"  stepping           implicitfast, Newton, one MuJoCo step per dt_s "
        f"(scene substeps {r['scene_substeps']}: rapier's, not used)",
        f"  model              {m['bodies']} bodies, {m['geoms']} geoms, {m['dofs']} dofs, "
        f"{m['actuators']} actuators, {m['rocks']} rocks, {m['heightfield'][0]}x{m['heightfield'][1]} hfield",
        f"  contacts           {r['contacts_end']} at the end, {r['contacts_mean']:.1f} mean",
        f"  drove              {r['displacement_m']:.2f} m (expected ~{r['expected_distance_m']:.2f} m = "
        f"{r['wheel_rate_rad_s']:g} rad/s x {r['wheel_radius_m']:.3f} m x {r['sim_s']:g} s; "
        f"ratio {r['distance_ratio']:.2f})",
        f"  upright            {'yes' if r['upright'] else 'NO'} (max tilt {r['max_tilt_deg']:.1f} deg, "
        f"final {r['final_tilt_deg']:.1f} deg)",
    ]
    if r["mujoco_warnings"]:
        lines.append(f"  MuJoCo warnings    {r['mujoco_warnings']}")
    print("\n".join(lines))


def main():
    ap = argparse.ArgumentParser(
        description="Time MuJoCo stepping the rover on an exported scene (see the module docstring).")
    ap.add_argument("--scene", required=True, help="SCENE.json exported by the twin")
    ap.add_argument("--urdf", required=True, help="the rover's URDF (assets/rover/rover.urdf)")
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds to time (after 1 s settling)")
    ap.add_argument("--json-out", help="also write the result as JSON here")
    ap.add_argument("--friction", type=float, default=0.8, help="sliding friction of every geom (0.8)")
    ap.add_argument(
        "--twin-config",
        help="twin.toml to take the actuator gains from (default: twin.toml beside the URDF, if any; "
        "'none' for the built-in values)")
    args = ap.parse_args()

    if args.seconds <= 0.0:
        print("mujoco_bench: --seconds must be positive", file=sys.stderr)
        return 2
    twin_cfg = args.twin_config
    if twin_cfg is None:
        candidate = os.path.join(os.path.dirname(os.path.abspath(args.urdf)), "twin.toml")
        twin_cfg = candidate if os.path.isfile(candidate) else None
    elif twin_cfg == "none":
        twin_cfg = None

    try:
        scene = load_scene(args.scene)
        result = run(scene, args.urdf, args.seconds, args.friction, twin_cfg)
    except BadInput as e:
        print(f"mujoco_bench: {e}", file=sys.stderr)
        return 2
    result["scene"] = os.path.abspath(args.scene)
    result["urdf"] = os.path.abspath(args.urdf)
    report(result)
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(result, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
