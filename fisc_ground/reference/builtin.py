"""Built-in reference fields: shipped CFD node fields (``field_maps/*.npz``) and the analytic one.

* ``cd_nozzle_inviscid`` (the embedded default): OpenFOAM laminar slip-wall solution of the
  DESIGN.md section 2 tunnel, the 3-D node field of its Fluent-style export (63539 nodes).
* ``cd_nozzle``: the RANS k-omega SST no-slip solution of the same tunnel; it separates on the
  diverging wall, so it holds reversed-flow nodes (u_x < 0) near the wall - kept on purpose.
* ``analytic``: the quasi-1-D isentropic field (computed on the fly, no data file).

The ``.npz`` files are written by ``tools/build_field_maps.py`` from ``../shared/reference`` and
hold the exact float64 values of the Fluent-style CSV, so a built-in equals
``read_fluent_csv(<that csv>)`` bit for bit; they are found with ``importlib.resources`` and need
nothing outside the installed package.
"""

from __future__ import annotations

import hashlib
import io
import json
from importlib import resources

import numpy as np

from fisc_ground.reference.analytic import analytic_nozzle
from fisc_ground.reference.field import ReferenceError, ReferenceField

#: Name of the embedded default reference.
DEFAULT_BUILTIN = "cd_nozzle_inviscid"
#: Built-ins shipped as data files in the ``field_maps`` package: name -> file name.
BUILTIN_FILES = {"cd_nozzle_inviscid": "cd_nozzle_inviscid.npz", "cd_nozzle": "cd_nozzle.npz"}
#: Built-ins computed on the fly.
COMPUTED_BUILTINS = ("analytic",)
#: Arrays every built-in ``.npz`` holds (plus ``provenance_json``, ``readme_md``).
NPZ_ARRAYS = ("points_m", "velocity_m_s", "pressure_gauge_pa", "density_kg_m3")
#: Version of the built-in ``.npz`` layout.
NPZ_FORMAT_VERSION = 1
DATA_PACKAGE = "field_maps"


def builtin_names() -> tuple[str, ...]:
    """Names accepted by :func:`load_builtin` (the default first)."""
    return (*BUILTIN_FILES, *COMPUTED_BUILTINS)


def load_builtin(name: str) -> ReferenceField:
    """Load a built-in reference field by name; unknown names raise :class:`ReferenceError`."""
    if name in COMPUTED_BUILTINS:
        return analytic_nozzle(name=name)
    if name not in BUILTIN_FILES:
        raise ReferenceError(f"builtin:{name}: unknown built-in reference; known: "
                             f"{', '.join(builtin_names())}")
    res = resources.files(DATA_PACKAGE) / BUILTIN_FILES[name]
    where = f"{DATA_PACKAGE}/{BUILTIN_FILES[name]}"
    try:
        blob = res.read_bytes()
    except FileNotFoundError as exc:
        raise ReferenceError(f"builtin:{name}: data file {where} is missing (regenerate it with "
                             "tools/build_field_maps.py)") from exc
    return field_from_npz_bytes(blob, name, where)


def field_from_npz_bytes(blob: bytes, name: str, where: str) -> ReferenceField:
    """Decode a built-in ``.npz`` (as written by :func:`npz_payload`) into a ReferenceField."""
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as z:
            missing = [k for k in (*NPZ_ARRAYS, "provenance_json") if k not in z.files]
            if missing:
                raise ReferenceError(f"builtin:{name}: {where} lacks array(s) {missing}")
            arrays = {k: np.asarray(z[k], dtype=np.float64) for k in NPZ_ARRAYS}
            prov = json.loads(str(z["provenance_json"]))
    except ReferenceError:
        raise
    except (ValueError, OSError, KeyError) as exc:
        raise ReferenceError(f"builtin:{name}: {where} is not a valid .npz: {exc}") from exc
    dens = arrays["density_kg_m3"]
    return ReferenceField(
        points_m=arrays["points_m"], velocity_m_s=arrays["velocity_m_s"],
        pressure_gauge_pa=arrays["pressure_gauge_pa"],
        density_kg_m3=None if dens.size == 0 else dens, name=name, source=f"builtin:{name}",
        source_sha256=str(prov.get("source_sha256", "")),
        pressure_kind=prov.get("pressure_kind", "gauge"),
        extras={"origin": prov.get("origin"), "summary": prov.get("summary"),
                "solver": prov.get("solver"), "field_map": where,
                "field_map_sha256": hashlib.sha256(blob).hexdigest()})


def npz_payload(field: ReferenceField, origin: str, summary: str, solver: str,
                readme_md: str) -> dict[str, np.ndarray]:
    """Arrays to pass to ``np.savez_compressed`` for a built-in (used by the build tool)."""
    prov = {"format_version": NPZ_FORMAT_VERSION, "origin": origin,
            "source_sha256": field.source_sha256, "pressure_kind": field.pressure_kind,
            "readme_sha256": hashlib.sha256(readme_md.encode()).hexdigest(),
            "summary": summary, "solver": solver, "n_nodes": field.n_nodes,
            "builder": "tools/build_field_maps.py"}
    dens = field.density_kg_m3 if field.density_kg_m3 is not None else np.zeros(0)
    return {"points_m": np.asarray(field.points_m, np.float64),
            "velocity_m_s": np.asarray(field.velocity_m_s, np.float64),
            "pressure_gauge_pa": np.asarray(field.pressure_gauge_pa, np.float64),
            "density_kg_m3": np.asarray(dens, np.float64),
            "provenance_json": np.array(json.dumps(prov, sort_keys=True)),
            "readme_md": np.array(readme_md)}
