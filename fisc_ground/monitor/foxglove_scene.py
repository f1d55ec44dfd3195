"""The swarm as Foxglove messages: topics, well-known schemas and the builders (arrays in, messages out).

Every FISC flight log (``fisc-ground monitor --foxglove/--record``, ``fisc-sim run --mcap``,
``fisc-sim emulate --mcap``) carries the same channels, in the map frame (``frame_id`` ``map``,
x along the tunnel axis, z up):

============================  =====================  ==============================================
topic                         schema                 content
============================  =====================  ==============================================
``/fisc/agents``              foxglove.PointCloud    one point per live agent: x, y, z, vx, vy, vz,
                                                     agent_id, state code, RGBA coloured by state
``/fisc/cvs``                 foxglove.PointCloud    one point per CV centre: running density
                                                     [kg/m^3], pressure [Pa], samples, RGBA by density
``/fisc/scene``               foxglove.SceneUpdate   the duct wall (lines), per-agent velocity arrows and
                                                     d_min spheres (radius d_min / 2)
``/fisc/fidelity``            JSON schema            running nRMSE / Pearson against the map's CFD targets
``/fisc/states``              JSON schema            live agents per state, stale agents
``/fisc/alarms``              JSON schema            the monitor's alarms (``fisc_ground.monitor.alarms``),
                                                     logged when they change
``/fisc/telemetry``           JSON schema            the raw telemetry stream (what replay re-aggregates)
``/fisc/map``                 JSON schema            the map flown (``.fiscmap`` bytes, base64)
``/fisc/settings``            JSON schema            the aggregator settings of the log
============================  =====================  ==============================================

``docs/foxglove_layout.json`` (``layout_json``) arranges them in the Foxglove app.
"""

from __future__ import annotations

import math

import numpy as np

from fisc_agent.zenoh import telemetry_codec as tc

FRAME_ID = "map"
TOPIC_AGENTS = "/fisc/agents"
TOPIC_CVS = "/fisc/cvs"
TOPIC_SCENE = "/fisc/scene"
TOPIC_FIDELITY = "/fisc/fidelity"
TOPIC_STATES = "/fisc/states"
TOPIC_ALARMS = "/fisc/alarms"
TOPIC_TELEMETRY = "/fisc/telemetry"
TOPIC_MAP = "/fisc/map"
TOPIC_SETTINGS = "/fisc/settings"

#: RGBA (0-255) of each telemetry state (``telemetry_codec.STATES``); unknown states grey.
STATE_RGBA = {
    "TAKEOFF": (255, 170, 0, 255), "JOIN": (0, 170, 255, 255), "FLOW": (40, 200, 80, 255),
    "RETURN": (255, 90, 200, 255), "EXIT": (150, 110, 255, 255), "HOLD": (230, 40, 40, 255),
    "LAND": (120, 120, 120, 255), "FAILSAFE": (255, 0, 0, 255),
}
_GREY = (180, 180, 180, 255)
_STATE_TABLE = np.array([STATE_RGBA.get(s, _GREY) for s in tc.STATES], dtype=np.uint8)

AGENT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vz", "<f4"),
                        ("agent_id", "<u4"), ("state", "u1"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                        ("alpha", "u1"), ("authority", "u1"), ("battery_pct", "u1"), ("health", "u1")])
"""One ``/fisc/agents`` point (velocity in [m/s], ``state`` a ``telemetry_codec.STATES`` index,
``authority`` an ``AUTHORITIES`` index, ``battery_pct`` 0-100 (255: not reported), ``health`` the
number of health problems)."""
CV_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("density_kg_m3", "<f4"), ("pressure_pa", "<f4"),
                     ("samples", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])
"""One ``/fisc/cvs`` point (NaN density/pressure where the CV has no sample yet)."""

_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=float)

_FLOAT_OR_NULL = {"type": ["number", "null"]}
FIDELITY_SCHEMA = {
    "title": "fisc.Fidelity", "type": "object",
    "description": "Running fidelity of the time-averaged swarm fields against the map's CFD targets "
                   "(DESIGN.md section 4; null while undefined)",
    "properties": {
        "t_s": {"type": "number", "description": "receive time of the estimate [s]"},
        "time_samples": {"type": "integer"}, "n_cv_compared": {"type": "integer"},
        **{f"{k}_{q}": _FLOAT_OR_NULL for k in ("nrmse", "pearson") for q in ("velocity", "pressure", "density")},
        "closest_approach_m": {**_FLOAT_OR_NULL, "description": "distance of the closest two live agents now [m]"},
        "d_min_m": {"type": "number", "description": "the map's designed spacing [m]"},
    },
}
ALARMS_SCHEMA = {
    "title": "fisc.Alarms", "type": "object", "description": "The monitor's alarms (empty list: none)",
    "properties": {"t_s": {"type": "number"}, "agents_heard": {"type": "integer"}, "stale": {"type": "integer"},
                   "alarms": {"type": "array", "items": {"type": "string"}},
                   "closest_approach_m": {**_FLOAT_OR_NULL,
                                          "description": "distance of the closest two live agents [m]"},
                   "d_min_m": {"type": "number", "description": "the spacing the separation alarm holds [m]"}},
    "required": ["t_s", "alarms"],
}
STATES_SCHEMA = {
    "title": "fisc.StateCounts", "type": "object", "description": "Live agents per mission state",
    "properties": {"t_s": {"type": "number"}, "agents_heard": {"type": "integer"}, "stale": {"type": "integer"},
                   **{s: {"type": "integer"} for s in tc.STATES}},
}
TELEMETRY_SCHEMA = {
    "title": "fisc.TelemetryBatch", "type": "object",
    "description": "Telemetry messages as the monitor received them, in order (fisc_agent.zenoh.telemetry_codec)",
    "properties": {"seq": {"type": "integer", "description": "position of this record in the log"},
                   "recv_s": {"type": "array", "items": {"type": "number"}, "description": "receive times [UNIX s]"},
                   "key_agent_id": {"type": "array", "items": {"type": "integer"},
                                    "description": "agent id from the Zenoh key (4294967295: none)"},
                   "payload_b64": {"type": "array", "items": {"type": "string"}}},
    "required": ["seq", "recv_s", "key_agent_id", "payload_b64"],
}
MAP_SCHEMA = {
    "title": "fisc.Map", "type": "object", "description": "The command map the log switched to at this point",
    "properties": {"seq": {"type": "integer"}, "recv_s": {"type": "number"}, "sha256": {"type": "string"},
                   "map_version": {"type": "integer"}, "map_b64": {"type": "string"}},
    "required": ["seq", "recv_s", "map_b64"],
}
SETTINGS_SCHEMA = {
    "title": "fisc.LogSettings", "type": "object", "description": "Aggregator settings of this flight log",
    "properties": {"source": {"type": "string"}, "swarm": {"type": ["string", "null"]},
                   "sample_period_s": {"type": "number"}, "stale_after_s": {"type": "number"},
                   "roster": {"type": ["string", "null"]}, "max_agents": {"type": "integer"},
                   "low_battery_pct": {"type": "number"},
                   "telemetry_version": {"type": "integer"}, "created_utc": {"type": "string"}},
    "required": ["sample_period_s", "stale_after_s"],
}


def _fg():
    from foxglove import messages

    return messages


def timestamp(t_s: float):
    """``foxglove.messages.Timestamp`` of a time in seconds (UNIX or run time)."""
    m = _fg()
    sec = math.floor(t_s)
    return m.Timestamp(sec=int(sec), nsec=min(int(round((t_s - sec) * 1e9)), 999_999_999))


def _fields(dtype: np.dtype) -> list:
    m = _fg()
    kinds = {"<f4": m.PackedElementFieldNumericType.Float32, "<u4": m.PackedElementFieldNumericType.Uint32,
             "|u1": m.PackedElementFieldNumericType.Uint8}
    return [m.PackedElementField(name=name, offset=dtype.fields[name][1], type=kinds[dtype.fields[name][0].str])
            for name in dtype.names]


def _cloud(t_s: float, points: np.ndarray):
    m = _fg()
    return m.PointCloud(timestamp=timestamp(t_s), frame_id=FRAME_ID, pose=_identity_pose(),
                        point_stride=points.dtype.itemsize, fields=_fields(points.dtype), data=points.tobytes())


def _identity_pose():
    m = _fg()
    return m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0), orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def agent_points(ids: np.ndarray, records: np.ndarray) -> np.ndarray:
    """``AGENT_DTYPE`` points of telemetry records (``telemetry_codec.DTYPE``) with a finite position."""
    pos = records["position_m"].astype(np.float32)
    vel = np.nan_to_num(records["velocity_m_s"].astype(np.float32))
    ok = np.isfinite(pos).all(axis=1)
    out = np.zeros(int(ok.sum()), dtype=AGENT_DTYPE)
    out["x"], out["y"], out["z"] = pos[ok].T
    out["vx"], out["vy"], out["vz"] = vel[ok].T
    out["agent_id"] = np.asarray(ids)[ok]
    state = np.minimum(records["state"][ok], len(tc.STATES) - 1)
    out["state"] = state
    rgba = _STATE_TABLE[state]
    out["red"], out["green"], out["blue"], out["alpha"] = rgba.T
    out["authority"] = records["authority"][ok]
    out["battery_pct"] = records["battery_pct"][ok]
    out["health"] = records["health_count"][ok]
    return out


def agents_cloud(t_s: float, points: np.ndarray):
    """``/fisc/agents`` PointCloud of ``agent_points``."""
    return _cloud(t_s, points)


def cv_points(centres_m: np.ndarray, density_kg_m3: np.ndarray, pressure_pa: np.ndarray,
              samples: np.ndarray) -> np.ndarray:
    """``CV_DTYPE`` points: each CV centre with its running density and pressure (NaN without samples),
    coloured by density (viridis, min-max over the CVs with samples; grey without)."""
    c = np.asarray(centres_m, dtype=float)
    has = np.asarray(samples) > 0
    rho = np.where(has, density_kg_m3, np.nan)
    out = np.zeros(c.shape[0], dtype=CV_DTYPE)
    out["x"], out["y"], out["z"] = c.T
    out["density_kg_m3"] = rho
    out["pressure_pa"] = np.where(has, pressure_pa, np.nan)
    out["samples"] = samples
    rgba = np.tile(np.array([120, 120, 120, 40], dtype=np.uint8), (c.shape[0], 1))
    if has.any():
        lo, hi = float(np.nanmin(rho)), float(np.nanmax(rho))
        x = (rho[has] - lo) / (hi - lo) if hi > lo else np.full(int(has.sum()), 0.5)
        rgba[has, :3] = _viridis(x)
        rgba[has, 3] = 200
    out["red"], out["green"], out["blue"], out["alpha"] = rgba.T
    return out


def _viridis(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.nan_to_num(x), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(x.astype(int), len(_VIRIDIS) - 2)
    f = (x - i)[:, None]
    return (_VIRIDIS[i] + f * (_VIRIDIS[i + 1] - _VIRIDIS[i])).astype(np.uint8)


def cvs_cloud(t_s: float, points: np.ndarray):
    """``/fisc/cvs`` PointCloud of ``cv_points``."""
    return _cloud(t_s, points)


def arrow_quaternions(vel: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (x, y, z, w) turning +x onto each velocity direction (identity for 0)."""
    v = np.asarray(vel, dtype=float)
    speed = np.linalg.norm(v, axis=1)
    u = np.divide(v, speed[:, None], out=np.tile([1.0, 0.0, 0.0], (len(v), 1)), where=speed[:, None] > 1e-9)
    q = np.stack([np.zeros(len(v)), -u[:, 2], u[:, 1], 1.0 + u[:, 0]], axis=1)  # half-way rotation
    back = q[:, 3] < 1e-9  # exactly -x: half a turn about z
    q[back] = (0.0, 0.0, 1.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def wall_lines(centres_m: np.ndarray, cell_m: float, radius_of_x=None, rings: int = 16, sides: int = 32) -> list:
    """Duct wall as (k, 3) polylines: with the design wall ``radius_of_x`` (``plots.design_tunnel_wall``)
    ``rings`` circles along x plus 8 generatrices; otherwise the box around the CVs."""
    c = np.asarray(centres_m, dtype=float)
    lo, hi = c.min(axis=0) - cell_m / 2, c.max(axis=0) + cell_m / 2
    if radius_of_x is None:
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        face = lambda x: np.array([[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1], [x, y0, z0]])  # noqa: E731
        edges = [np.array([[x0, y, z], [x1, y, z]]) for y in (y0, y1) for z in (z0, z1)]
        return [face(x0), face(x1), *edges]
    xs = np.linspace(lo[0], hi[0], 200)
    r = np.asarray(radius_of_x(xs), dtype=float)
    lines = []
    for x in np.linspace(lo[0], hi[0], rings):
        rr = float(radius_of_x(np.array([x]))[0])
        a = np.linspace(0.0, 2 * np.pi, sides + 1)
        lines.append(np.stack([np.full_like(a, x), rr * np.cos(a), rr * np.sin(a)], axis=1))
    for a in np.linspace(0.0, 2 * np.pi, 9)[:-1]:
        lines.append(np.stack([xs, r * np.cos(a), r * np.sin(a)], axis=1))
    return lines


def scene_update(t_s: float, wall: list, points: np.ndarray, arrow_s: float = 0.5, d_min_m: float | None = None):
    """``/fisc/scene`` SceneUpdate: entity ``duct_wall`` (the wall polylines), entity ``velocity``
    (one arrow per agent point, length = speed * ``arrow_s``, coloured by state) and, given ``d_min_m``,
    entity ``d_min``: one translucent sphere of radius d_min / 2 per agent (two spheres that touch are
    two vehicles at d_min; overlapping ones are closer)."""
    m = _fg()
    ts = timestamp(t_s)
    grey = m.Color(r=0.6, g=0.6, b=0.65, a=0.6)
    wall_entity = m.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id="duct_wall", lines=[
        m.LinePrimitive(type=m.LinePrimitiveLineType.LineStrip, pose=_identity_pose(), thickness=1.5,
                        scale_invariant=True, color=grey,
                        points=[m.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in line])
        for line in wall])
    vel = np.stack([points["vx"], points["vy"], points["vz"]], axis=1).astype(float)
    speed = np.linalg.norm(vel, axis=1)
    quat = arrow_quaternions(vel)
    arrows = []
    for p, s, q in zip(points.tolist(), speed.tolist(), quat.tolist()):
        length = max(s * arrow_s, 1e-3)
        arrows.append(m.ArrowPrimitive(
            pose=m.Pose(position=m.Vector3(x=p[0], y=p[1], z=p[2]),
                        orientation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])),
            shaft_length=0.7 * length, shaft_diameter=0.05, head_length=0.3 * length, head_diameter=0.12,
            color=m.Color(r=p[8] / 255, g=p[9] / 255, b=p[10] / 255, a=1.0)))
    arrow_entity = m.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id="velocity", arrows=arrows)
    entities = [wall_entity, arrow_entity]
    if d_min_m is not None and d_min_m > 0:
        size = m.Vector3(x=float(d_min_m), y=float(d_min_m), z=float(d_min_m))  # diameter d_min
        entities.append(m.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id="d_min", spheres=[
            m.SpherePrimitive(pose=m.Pose(position=m.Vector3(x=p[0], y=p[1], z=p[2]),
                                          orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                              size=size, color=m.Color(r=p[8] / 255, g=p[9] / 255, b=p[10] / 255, a=0.15))
            for p in points.tolist()]))
    return m.SceneUpdate(entities=entities)


def layout_json() -> str:
    """The Foxglove layout shipped as ``docs/foxglove_layout.json``: the 3-D swarm (agents by state,
    velocity arrows, wall, CVs by density) beside the CVs by pressure, the running nRMSE and the
    counts by state."""
    import foxglove.layouts as fl

    def three_d(color_field: str, title: str, agents: bool):
        topics = {TOPIC_CVS: fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=6.0, color_field=color_field, color_mode="colormap", color_map="turbo"),
            TOPIC_SCENE: fl.BaseRendererSceneUpdateTopicSettings(visible=True)}
        if agents:
            topics[TOPIC_AGENTS] = fl.BaseRendererPointCloudTopicSettings(visible=True, point_size=10.0,
                                                                          color_mode="rgba-fields")
        return fl.ThreeDeePanel(title=title, config=fl.ThreeDeeConfig(follow_tf=FRAME_ID, topics=topics))

    plot = lambda title, series: fl.PlotPanel(title=title, config=fl.PlotConfig(paths=[  # noqa: E731
        fl.PlotSeries(value=v, label=lab) for v, lab in series]))
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d("density_kg_m3", "swarm, CVs by density", True)),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(content=three_d("pressure_pa", "CVs by pressure", False)),
            fl.SplitItem(content=plot("running nRMSE vs CFD", [
                (f"{TOPIC_FIDELITY}.nrmse_{q}", q) for q in ("velocity", "pressure", "density")])),
            fl.SplitItem(content=plot("agents by state", [
                (f"{TOPIC_STATES}.{s}", s) for s in ("TAKEOFF", "JOIN", "FLOW", "RETURN", "HOLD")]
                + [(f"{TOPIC_STATES}.stale", "stale")])),
        ])),
    ])).to_json()
