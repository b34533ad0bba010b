"""The SPEC of ``spctool simulate``: read, validated, completed with defaults and sized before anything
is built.

Specification: spc-algorithms.md §12.2 (the synthetic world S16 built with Gaskell's codes) as
:mod:`spctool.sim.simulate` builds it.  The keys, their defaults, kinds and help texts are one table,
:data:`spctool.sim.spec_keys.SPEC_KEYS` (plain data, so that ``--help`` shows it without loading the
simulator); this module reads a SPEC with it:

* :func:`load_spec` — a SPEC.toml (UTF-8, at most :data:`MAX_SPEC_BYTES`), every problem one line naming
  the file and what was expected;
* :func:`parse_spec` — a mapping (as TOML reads it) → :class:`Spec`: unknown sections and keys refused,
  values converted to their kind, defaults filled in, picture names derived, cross-checks (powers of 2,
  name lengths, detector bits …);
* :func:`memory_estimate`, :func:`check_memory` — the peak memory of the world from its sizes alone, so
  that a SPEC too large for the machine is refused before anything is allocated (``--max-memory``).
"""

from __future__ import annotations

import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

from spctool.errors import SpcUsageError
from spctool.formats.guard import check_allocation, check_name
from spctool.sim.spec_keys import DEFAULT_PICTURES, PHOTO_SUFFIX, PICTURE_KEYS, SPEC_KEYS

__all__ = [
    "MAX_SPEC_BYTES",
    "Spec",
    "check_memory",
    "default_max_memory",
    "load_spec",
    "memory_estimate",
    "parse_spec",
]


def _convert(kind: str, value, where: str):
    def bad(expected):
        return SpcUsageError(f"SPEC {where}: expected {expected}, got {value!r}")

    try:
        if kind == "int":
            if isinstance(value, bool) or not float(value).is_integer():
                raise bad("an integer")
            return int(value)
        if kind == "float":
            if isinstance(value, bool):
                raise bad("a number")
            return float(value)
        if kind == "bool":
            if not isinstance(value, bool):
                raise bad("true or false")
            return value
        if kind == "str":
            if not isinstance(value, str):
                raise bad("a string")
            return value
        if kind == "vec3":
            out = [float(v) for v in value]
            if len(out) != 3:
                raise bad("3 numbers")
            return out
        if kind == "floats":
            return [float(v) for v in value]
        if kind == "strs":
            return [str(v) for v in value]
        if kind == "latlons":
            out = [[float(a), float(b)] for a, b in value]
            return out
        if kind == "kmatrix":
            out = [[float(v) for v in row] for row in value]
            if len(out) != 2 or any(len(r) != 3 for r in out):
                raise bad("a 2x3 matrix [[K11, K12, K13], [K21, K22, K23]]")
            return out
        if kind == "exposure":
            if isinstance(value, str):
                if value != "auto":
                    raise bad("'auto' or a number")
                return value
            return float(value)
    except (TypeError, ValueError):
        raise bad(kind) from None
    raise AssertionError(kind)


@dataclass
class Spec:
    """A resolved SPEC: ``sections[name]`` namespaces (``"" ``, ``"body"``, ``"terrain.craters"`` …),
    ``pictures`` (list of namespaces) and the directory relative paths are resolved against."""

    sections: dict[str, SimpleNamespace]
    pictures: list[SimpleNamespace]
    base: Path = field(default_factory=lambda: Path("."))

    def __getattr__(self, name):
        secs = self.__dict__.get("sections", {})
        if name in secs:
            return secs[name]
        raise AttributeError(name)

    @property
    def seed(self) -> int:
        return self.sections[""].seed

    @property
    def landmark_count(self) -> int:
        """Landmarks of the world: one per ``[maplets] positions`` entry, else per name, else ``count``."""
        m = self.sections["maplets"]
        if m.positions:
            return len(m.positions)
        if m.names:
            return len(m.names)
        return int(m.count)

    def to_dict(self) -> dict:
        """The resolved specification as plain data (TOML-like nesting)."""
        out: dict = {}
        for sec, ns in self.sections.items():
            target = out
            if sec:
                for part in sec.split("."):
                    target = target.setdefault(part, {})
            target.update(vars(ns))
        out["pictures"] = [dict(vars(p)) for p in self.pictures]
        return out


def parse_spec(data: dict, base=".", where: str = "SPEC") -> Spec:
    """Validate a SPEC mapping (as read from TOML), fill defaults, derive names; see :data:`SPEC_KEYS`."""
    data = dict(data or {})
    known_sections = list(dict.fromkeys(s for s, *_ in SPEC_KEYS))  # ordered: TRUTH.json is byte-stable
    flat: dict[str, dict] = {s: {} for s in known_sections}
    pictures_raw = data.pop("pictures", None)

    def walk(prefix, mapping):
        for k, v in mapping.items():
            name = f"{prefix}.{k}" if prefix else k
            if isinstance(v, dict):
                if name not in known_sections and not any(s.startswith(name + ".") for s in known_sections):
                    raise SpcUsageError(f"{where}: unknown section [{name}]")
                walk(name, v)
            else:
                if prefix not in known_sections:
                    raise SpcUsageError(f"{where}: unknown key {name!r}")
                flat[prefix][k] = v

    walk("", data)
    sections: dict[str, SimpleNamespace] = {}
    keys_by_section: dict[str, dict] = {}
    for section, key, default, kind, _ in SPEC_KEYS:
        keys_by_section.setdefault(section, {})[key] = (default, kind)
    for section, given in flat.items():
        known = keys_by_section[section]
        for k in given:
            if k not in known:
                label = f"[{section}] {k}" if section else k
                raise SpcUsageError(f"{where}: unknown key {label!r} (see 'spctool simulate --help')")
        values = {}
        for k, (default, kind) in known.items():
            label = f"[{section}] {k}" if section else k
            values[k] = (
                _convert(kind, given[k], f"{where} {label}")
                if k in given
                else json.loads(json.dumps(default))
            )
        sections[section] = SimpleNamespace(**values)
    # pictures
    if pictures_raw is None:
        pictures_raw = [dict(p) for p in DEFAULT_PICTURES]
    if not isinstance(pictures_raw, list) or not pictures_raw:
        raise SpcUsageError(f"{where}: [[pictures]] must list at least one picture")
    pk = {k: (d, kind) for k, d, kind, _ in PICTURE_KEYS}
    pictures = []
    for i, raw in enumerate(pictures_raw):
        if not isinstance(raw, dict):
            raise SpcUsageError(f"{where}: pictures[{i}] must be a table")
        for k in raw:
            if k not in pk:
                raise SpcUsageError(f"{where}: unknown key {k!r} in pictures[{i}]")
        vals = {}
        for k, (default, kind) in pk.items():
            if k in raw:
                vals[k] = _convert(kind, raw[k], f"{where} pictures[{i}].{k}")
            else:
                vals[k] = default
        if not vals["name"]:
            vals["name"] = f"P{i + 1:09d}A1"
        if len(vals["name"]) > 12 or not vals["name"].strip():
            raise SpcUsageError(f"{where}: picture name {vals['name']!r} must have 1 to 12 characters")
        _plain(vals["name"], f"{where}: pictures[{i}].name")
        if vals["view_lat_deg"] is None:
            vals["view_lat_deg"] = vals["aim_lat_deg"]
        if vals["view_lon_deg"] is None:
            vals["view_lon_deg"] = vals["aim_lon_deg"]
        if not vals["utc"]:
            t0 = 10 * i
            vals["utc"] = f"2024 JAN 01 {t0 // 60:02d}:{t0 % 60:02d}:00.000"
        vals["format"] = vals["format"].lower()
        if vals["format"] not in PHOTO_SUFFIX:
            raise SpcUsageError(f"{where}: pictures[{i}].format must be one of {', '.join(PHOTO_SUFFIX)}")
        if vals["bits"] == 0:
            vals["bits"] = sections["detector"].bits
        if vals["bits"] not in (8, 16):
            raise SpcUsageError(f"{where}: pictures[{i}].bits must be 8 or 16")
        if vals["format"] == "dat" and vals["bits"] == 8:
            pass  # 8-bit DAT is legal (NPX*NLN bytes)
        if not vals["range_km"] > 0:
            raise SpcUsageError(f"{where}: pictures[{i}].range_km must be > 0")
        pictures.append(SimpleNamespace(**vals))
    names = [p.name for p in pictures]
    if len(set(names)) != len(names):
        raise SpcUsageError(f"{where}: picture names must be unique")
    spec = Spec(sections, pictures, Path(base))
    _check(spec, where)
    return spec


def _check(spec: Spec, where: str):
    b, m, c, d = spec.body, spec.maplets, spec.camera, spec.detector
    if b.q < 2 or b.q & (b.q - 1):
        raise SpcUsageError(f"{where}: [body] q must be a power of 2 >= 2, got {b.q}")
    if not b.shape and min(b.radii_km) <= 0:
        raise SpcUsageError(f"{where}: [body] radii_km must be positive")
    if m.count < 0:
        raise SpcUsageError(f"{where}: [maplets] count must be >= 0")
    if m.qsz < 2 or m.truth_factor < 1 or m.margin < 0 or not m.scale_km > 0:
        raise SpcUsageError(
            f"{where}: [maplets] needs qsz >= 2, truth_factor >= 1, margin >= 0, scale_km > 0"
        )
    if m.names and m.positions and len(m.names) != len(m.positions):
        raise SpcUsageError(f"{where}: [maplets] names and positions must have the same length")
    for n in m.names:
        if not 1 <= len(n) <= 6:
            raise SpcUsageError(f"{where}: landmark name {n!r} must have 1 to 6 characters")
        _plain(n, f"{where}: [maplets] names")
    if m.prefix:
        _plain(m.prefix, f"{where}: [maplets] prefix")
    if len(set(m.names)) != len(m.names):
        raise SpcUsageError(f"{where}: landmark names must be unique")
    if c.npx < 2 or c.nln < 2 or not c.mmfl > 0:
        raise SpcUsageError(f"{where}: [camera] needs npx, nln >= 2 and mmfl > 0")
    if c.ctr and len(c.ctr) != 2:
        raise SpcUsageError(f"{where}: [camera] ctr must be [sample, line]")
    if d.bits not in (8, 16):
        raise SpcUsageError(f"{where}: [detector] bits must be 8 or 16")
    if not 1 <= d.supersample <= 16:
        raise SpcUsageError(f"{where}: [detector] supersample must be 1 ... 16")
    from spctool.stages.render import RenderOptions  # lazily: the renderer loads numba

    RenderOptions(photometry=d.photometry)  # validates the model name
    if spec.sections[""].seed < 0:
        raise SpcUsageError(f"{where}: seed must be >= 0")


def _plain(name: str, where: str) -> None:
    """A picture or landmark name becomes a file name: a plain identifier only (guard.check_name)."""
    try:
        check_name(name, "name")
    except SpcUsageError as exc:
        raise SpcUsageError(f"{where}: {exc}") from None


#: largest SPEC.toml read (bytes): a SPEC is a few hundred lines
MAX_SPEC_BYTES = 1 << 20


def load_spec(path) -> Spec:
    """Read and validate a SPEC.toml (UTF-8, at most :data:`MAX_SPEC_BYTES`)."""
    from spctool.errors import SpcFormatError
    from spctool.formats.guard import read_bytes

    path = Path(path)
    try:
        raw = read_bytes(path, "a SPEC file", max_bytes=MAX_SPEC_BYTES)
    except SpcFormatError as exc:
        raise SpcUsageError(str(exc)) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpcUsageError(
            f"{path}: byte {exc.start}: expected UTF-8 text (TOML), found byte 0x{raw[exc.start]:02x}"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpcUsageError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise SpcUsageError(f"{path}: not valid TOML: nested too deeply") from None
    except ValueError:  # tomllib refuses integers of more than 4300 digits
        raise SpcUsageError(f"{path}: not valid TOML: numbers of at most 4300 digits expected") from None
    return parse_spec(data, base=path.parent, where=str(path))



# ---- memory: sizes checked before anything is allocated ----------------------------------------

#: bytes per node of the truth patches (all landmarks at once: positions, heights, albedo, terrain
#: temporaries), per ICQ vertex of the global shape (vertices, triangles, ray-tracing hierarchy), per
#: photo pixel (DN, radiance, coverage of every picture) and per ray of one render; measured peak
#: resident sizes (`/usr/bin/time -f %M`) of worlds scaled in each size, rounded up
_BYTES_PER_TRUTH_NODE = 320
_BYTES_PER_VERTEX = 480
_BYTES_PER_PIXEL = 64
_BYTES_PER_RAY = 48
_BASE_BYTES = 400 * 1024**2


def default_max_memory() -> int:
    """Half the physical memory (the default ``--max-memory``), 4 GiB when it cannot be known."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2)
    except (AttributeError, ValueError, OSError):  # pragma: no cover - not POSIX
        return 4 * 1024**3


def memory_estimate(spec: Spec) -> dict[str, float]:
    """Peak memory (bytes) of each part of :func:`build_world` / :func:`simulate` for ``spec``,
    from the sizes alone (nothing allocated): ``shape``, ``truth``, ``photos``, ``total``."""
    b, m, c, d = spec.body, spec.maplets, spec.camera, spec.detector
    count = spec.landmark_count
    n_truth = 2 * m.truth_factor * (m.qsz + m.margin) + 1
    shape = 6.0 * (float(b.q) + 1) ** 2 * _BYTES_PER_VERTEX
    truth = float(count) * float(n_truth) ** 2 * _BYTES_PER_TRUTH_NODE
    pixels = float(c.npx) * float(c.nln)
    photos = pixels * len(spec.pictures) * _BYTES_PER_PIXEL + pixels * d.supersample**2 * _BYTES_PER_RAY
    return {"shape": shape, "truth": truth, "photos": photos, "total": _BASE_BYTES + shape + truth + photos}


def check_memory(spec: Spec, limit: int | None = None, where: str = "SPEC") -> None:
    """SpcUsageError naming the largest part when :func:`memory_estimate` exceeds ``limit`` bytes
    (default :func:`default_max_memory`)."""
    limit = default_max_memory() if limit is None else int(limit)
    est = memory_estimate(spec)
    part = max(("shape", "truth", "photos"), key=lambda k: est[k])
    what = {
        "shape": "[body] q",
        "truth": "the truth patches ([maplets] count, qsz, margin, truth_factor)",
        "photos": "the photos ([camera] npx, nln, [detector] supersample, pictures)",
    }[part]
    check_allocation(
        est["total"],
        f"the world of {where}",
        limit,
        hint=f" (--max-memory); most of it for {what}",
    )
