"""Fuzzing of the text readers (issue 15): mutated CARMEN logs, KITTI side files and frames, relations, TUM,
g2o and configuration files must read cleanly (:func:`tests.fuzz.properties.reads_cleanly`).

Each property starts from small valid files written in a temporary folder (and, when the shared data is
there, the first records of a real log read in place) and applies a few mutations: byte flips, truncations,
inserted, deleted or duplicated lines, tokens replaced by non-finite, huge or malformed numbers, dropped or
added fields, non-UTF-8 bytes. Configuration files also get YAML's odd scalars (dates, timestamps,
``!!binary``, ``!!set``, 5000-digit and hexadecimal numbers, tags the safe loader refuses, escapes of control
characters) as the value, list item or key of every configuration key. Every crash found is kept under
``corpus/text/`` and replayed by :func:`test_corpus_reads_cleanly`.
"""

from __future__ import annotations

import bz2
import gzip
import itertools
import tempfile
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import BaseModel

from datasets.carmen import match_keyframe_scans, read_carmen
from datasets.config import InputConfig
from datasets.kitti import read_kitti
from datasets.paths import SHARED_DATA_DIR
from datasets.relations import read_relations
from datasets.types import Recording
from pipeline.config import Config, load_config
from slam.trajectory_io import read_g2o, read_tum
from tests.fuzz.properties import CORPUS, YAML_ODD_SCALARS, reads_cleanly

TEXT_CORPUS = CORPUS / "text"
SHARED_DATA = SHARED_DATA_DIR

#: Tokens that broke or could break a number parser: non-finite, huge, tiny, beyond int64, malformed.
NASTY = [
    "nan", "NaN", "inf", "-inf", "1e309", "-1e309", "1e30", "-1e30", "1e300", "99999999999999999999999",
    "1e9999999", "-1e9999999", "1e-9999999", "18446744073709551616", "9223372036854775808", "1000000000000",
    "0", "-0", "-1", "1e-320", "0.0000000001", "1.0.0", "", "x", "0x10", "1_0", "+", "-", ".", "e5", "1e",
    "\xff", "\u00b2", "\u0663", "3.5e38", "9000000000", "-9000000000", "1.7e308", "-1.7e308", "1e6", "-1e7",
]  # fmt: skip

# ------------------------------------------------------------------------------------------- seeds


def _flaser(ipc: float, ranges: str = "1.0 2.5 3.25 81.83", pose: str = "1.0 2.0 0.5") -> str:
    n = len(ranges.split())
    return f"FLASER {n} {ranges} {pose} {pose} {ipc:.6f} host {ipc:.6f}"


def _odom(ipc: float, pose: str = "1.0 2.0 0.5") -> str:
    return f"ODOM {pose} 0.1 0.0 0.0 {ipc:.6f} host {ipc:.6f}"


def _robotlaser(ipc: float) -> str:
    return (
        "ROBOTLASER1 0 -1.570796 3.141593 1.047198 81.9 0.01 0 4 1.5 2.5 81.91 3.0 0 "
        f"0.1 0.0 0.0 1.0 2.0 0.5 0.0 0.0 0.55 0.3 0.2 {ipc:.6f} host {ipc:.6f}"
    )


CARMEN_SEEDS: dict[str, str] = {
    "flaser_odom.clf": "\n".join(
        ["# CARMEN log", "PARAM robot_frontlaser_offset 0.0 nohost 0.0"]
        + [line for k in range(4) for line in (_flaser(10.0 + 0.2 * k), _odom(10.1 + 0.2 * k))]
    )
    + "\n",
    "robotlaser.clf": "\n".join(_robotlaser(5.0 + 0.1 * k) for k in range(4)) + "\n",
    "keyframes.gfs.log": "\n".join(
        [_odom(0.0, "0 0 0"), _odom(-0.5, "0 0 0")]
        + [_flaser(1.0 + k, pose=f"{k}.5 0.25 0.1") for k in range(3)]
    )
    + "\n",
}


REAL_SEEDS = {  # name -> (file in the shared data, opener): the first records, read in place
    "intel.gfs.log": ("intel/intel.gfs.log", open),
    "fr-clinic.clf": ("fr-clinic/fr-clinic_robotlaser.clf.bz2", bz2.open),
}


@cache
def _real_carmen_seed(name: str) -> str | None:
    """The first ODOM and laser records of a real log, read in place (None if the data is absent)."""
    relative, opener = REAL_SEEDS[name]
    path = SHARED_DATA / relative
    if not path.is_file():
        return None
    with opener(path, "rb") as f:
        head = list(itertools.islice(f, 3000))
    odom = [line for line in head if line.startswith(b"ODOM")][:20]
    laser = [line for line in head if line.startswith((b"FLASER", b"ROBOTLASER1"))][:3]
    return b"".join(odom + laser).decode("ascii") if laser else None


RELATIONS_SEED = (
    "# t1 t2 x y z roll pitch yaw\n"
    "976052857.337530 976052858.9 0.5 -0.01 0 0 0 0.02\n"
    "976052858.9 976052860.25 0.49 0.02 0 0 0 -0.015\n"
    "976052860.25 976052862 1.1 0.4 0 0 0 1.57\n"
)
TUM_SEED = (
    "# t x y z qx qy qz qw\n"
    "1.000000000 0.0 0.0 0.0 0.0 0.0 0.0 1.0\n"
    "1.100000000 0.1 0.01 0.0 0.0 0.0 0.0499792 0.9987503\n"
    "1.200000000 0.2 0.04 0.0 0.0 0.0 0.0998334 0.9950042\n"
)
G2O_SEED = (
    "VERTEX_SE2 0 0.0 0.0 0.0\n"
    "VERTEX_SE2 1 1.0 0.1 0.05\n"
    "VERTEX_SE2 2 2.0 0.3 0.1\n"
    "EDGE_SE2 0 1 1.0 0.1 0.05 100.0 0.0 0.0 100.0 0.0 400.0\n"
    "EDGE_SE2 1 2 1.0 0.2 0.05 100.0 0.0 0.0 100.0 0.0 400.0\n"
    "EDGE_SE2 0 2 2.0 0.3 0.1 50.0 1.0 0.0 50.0 0.0 200.0\n"
    "FIX 0\n"
)
CONFIG_SEED = (
    "input:\n  carmen_laser: auto\n  carmen_range_max_m: 80.0\n  carmen_stamp_jitter_s: 1.0\n"
    "mapping:\n  resolution_m: 0.1\n  mapper: gpfol\n"
    "scale:\n  workers: 2\n"
)
KITTI_SEEDS = {
    "calib.txt": "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n",
    "poses.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.1 0 1 0 0 0 0 1 0.8\n",
    "times.txt": "0.000000e+00\n1.036224e-01\n",
}


def _kitti_frame(seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-20, 20, size=(24, 4)).astype(np.float32)
    pts[:, 2] = rng.uniform(-1.5, 0.5, size=24)
    return pts.tobytes()


# --------------------------------------------------------------------------------------- mutations

_OP = st.one_of(
    st.tuples(st.just("token"), st.integers(0, 10**6), st.integers(0, 10**6), st.sampled_from(NASTY)),
    st.tuples(st.just("drop_token"), st.integers(0, 10**6), st.integers(0, 10**6)),
    st.tuples(st.just("add_token"), st.integers(0, 10**6), st.integers(0, 10**6), st.sampled_from(NASTY)),
    st.tuples(st.just("flip"), st.integers(0, 10**6), st.integers(1, 255)),
    st.tuples(st.just("truncate"), st.integers(0, 10**6)),
    st.tuples(st.just("delete_line"), st.integers(0, 10**6)),
    st.tuples(st.just("dup_line"), st.integers(0, 10**6), st.integers(0, 10**6)),
    st.tuples(st.just("insert"), st.integers(0, 10**6), st.binary(max_size=24)),
    st.tuples(st.just("swap_lines"), st.integers(0, 10**6), st.integers(0, 10**6)),
)
MUTATIONS = st.lists(_OP, min_size=1, max_size=4)


def mutate(data: bytes, ops: list[tuple]) -> bytes:
    """``data`` after the mutations ``ops`` (positions taken modulo the current sizes: any op applies)."""
    for op in ops:
        kind = op[0]
        lines = data.split(b"\n")
        if kind in ("token", "drop_token", "add_token"):
            i = op[1] % len(lines)
            toks = lines[i].split(b" ")
            j = op[2] % len(toks)
            if kind == "token":
                toks[j] = op[3].encode("utf-8")
            elif kind == "drop_token":
                del toks[j]
            else:
                toks.insert(j, op[3].encode("utf-8"))
            lines[i] = b" ".join(toks)
            data = b"\n".join(lines)
        elif kind == "flip" and data:
            at = op[1] % len(data)
            data = data[:at] + bytes([data[at] ^ op[2]]) + data[at + 1 :]
        elif kind == "truncate":
            data = data[: op[1] % (len(data) + 1)]
        elif kind == "delete_line" and len(lines) > 1:
            del lines[op[1] % len(lines)]
            data = b"\n".join(lines)
        elif kind == "dup_line":
            lines.insert(op[2] % (len(lines) + 1), lines[op[1] % len(lines)])
            data = b"\n".join(lines)
        elif kind == "insert":
            at = op[1] % (len(data) + 1)
            data = data[:at] + op[2] + data[at:]
        elif kind == "swap_lines":
            i, j = op[1] % len(lines), op[2] % len(lines)
            lines[i], lines[j] = lines[j], lines[i]
            data = b"\n".join(lines)
    return data


# ---------------------------------------------------------------------------------------- readers


def _read_kitti_fully(path: Path) -> Recording:
    """The KITTI recording with every cloud and scan read (their errors are raised lazily otherwise)."""
    rec = read_kitti(path)
    for i in range(len(rec.clouds)):
        rec.clouds[i]
    for ranges in rec.scans.ranges_m[:]:
        assert ranges.dtype == np.float32
    return rec


def _read_tum_checked(path: Path) -> tuple:
    stamps, poses = read_tum(path)
    assert stamps.dtype == np.int64 and np.isfinite(poses).all()
    return stamps, poses


def _read_g2o_checked(path: Path) -> object:
    graph = read_g2o(path)
    assert np.isfinite(graph.vertices_xytheta).all()
    assert all(np.isfinite(e.cov).all() and np.isfinite(e.measurement_xytheta).all() for e in graph.edges)
    return graph


def _read_relations_checked(path: Path) -> object:
    rel = read_relations(path)
    assert np.isfinite(rel.xyz_m).all() and np.isfinite(rel.rpy_rad).all()
    return rel


READERS: dict[str, Callable[[Path], object]] = {
    "carmen": read_carmen,
    "kitti": _read_kitti_fully,
    "relations": _read_relations_checked,
    "tum": _read_tum_checked,
    "g2o": _read_g2o_checked,
    "config": load_config,
}


def _pack(data: bytes, container: str) -> bytes:
    if container == "gz":
        return gzip.compress(data, mtime=0)
    if container == "bz2":
        return bz2.compress(data)
    return data


# -------------------------------------------------------------------------------------- properties


@given(
    seed=st.sampled_from([*CARMEN_SEEDS, *REAL_SEEDS]),
    ops=MUTATIONS,
    container=st.sampled_from(["plain", "gz", "bz2"]),
    mutate_packed=st.booleans(),
)
def test_carmen_mutations_read_cleanly(
    seed: str, ops: list[tuple], container: str, mutate_packed: bool
) -> None:
    text = CARMEN_SEEDS.get(seed) or _real_carmen_seed(seed) or CARMEN_SEEDS["keyframes.gfs.log"]
    data = text.encode()
    packed = mutate(_pack(data, container), ops) if mutate_packed else _pack(mutate(data, ops), container)
    name = seed + ("" if container == "plain" else f".{container}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(packed)
        reads_cleanly(lambda: read_carmen(path))


@given(
    seed=st.sampled_from(list(CARMEN_SEEDS)),
    line=st.integers(0, 40),
    field=st.integers(0, 40),
    token=st.sampled_from(NASTY),
)
def test_carmen_one_nasty_number_reads_cleanly(seed: str, line: int, field: int, token: str) -> None:
    """Exactly one field of a valid log replaced: every field of every record kind meets every nasty token."""
    data = mutate(CARMEN_SEEDS[seed].encode(), [("token", line, field, token)])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / seed
        path.write_bytes(data)
        reads_cleanly(lambda: read_carmen(path))


@given(
    target=st.sampled_from(["calib.txt", "poses.txt", "times.txt", "000000.bin", "000001.bin"]),
    ops=MUTATIONS,
    drop=st.sampled_from([None, "calib.txt", "poses.txt", "times.txt"]),
    single=st.booleans(),
)
def test_kitti_mutations_read_cleanly(target: str, ops: list[tuple], drop: str | None, single: bool) -> None:
    files = {**{k: v.encode() for k, v in KITTI_SEEDS.items()}, "000000.bin": _kitti_frame(0)}
    files["000001.bin"] = _kitti_frame(1)
    files[target] = mutate(files[target], ops)
    if drop is not None and drop != target:
        del files[drop]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name, data in files.items():
            (folder / name).write_bytes(data)
        path = folder / "000001.bin" if single else folder
        reads_cleanly(lambda: _read_kitti_fully(path))


@given(values=st.lists(st.sampled_from([*NASTY, "1", "0.5", "-2"]), min_size=4, max_size=4))
def test_kitti_frame_values_read_cleanly(values: list[str]) -> None:
    """Frames of non-finite, huge and tiny float32 values."""
    with np.errstate(all="ignore"):
        row = [np.float32(float(v)) if _is_float(v) else np.float32(1.0) for v in values]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "000000.bin"
        path.write_bytes(np.array([row, [1.0, 2.0, 0.0, 0.5]], dtype=np.float32).tobytes())
        reads_cleanly(lambda: _read_kitti_fully(path))


@given(fmt=st.sampled_from(["relations", "tum", "g2o", "config"]), ops=MUTATIONS)
def test_text_file_mutations_read_cleanly(fmt: str, ops: list[tuple]) -> None:
    seed, name = {
        "relations": (RELATIONS_SEED, "r.relations"),
        "tum": (TUM_SEED, "t.tum"),
        "g2o": (G2O_SEED, "g.g2o"),
        "config": (CONFIG_SEED, "c.yaml"),
    }[fmt]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(mutate(seed.encode(), ops))
        reads_cleanly(lambda: READERS[fmt](path))


@given(
    fmt=st.sampled_from(["relations", "tum", "g2o"]),
    line=st.integers(0, 10),
    field=st.integers(0, 12),
    token=st.sampled_from(NASTY),
)
def test_text_file_one_nasty_number_reads_cleanly(fmt: str, line: int, field: int, token: str) -> None:
    seed = {"relations": RELATIONS_SEED, "tum": TUM_SEED, "g2o": G2O_SEED}[fmt]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"f.{fmt}"
        path.write_bytes(mutate(seed.encode(), [("token", line, field, token)]))
        reads_cleanly(lambda: READERS[fmt](path))


@given(
    stage=st.sampled_from(["input", "mapping", "scale", "slam"]),
    key=st.sampled_from(["resolution_m", "carmen_stamp_jitter_s", "carmen_range_max_m", "workers", "mapper"]),
    value=st.one_of(
        st.sampled_from(NASTY),
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(min_value=-(2**70), max_value=2**70),
        st.none(),
    ),
)
def test_config_overrides_read_cleanly(stage: str, key: str, value: object) -> None:
    """Command-line overrides of any value: a ConfigError naming the option, never a traceback."""
    reads_cleanly(lambda: load_config(None, {stage: {key: value}}))


def _config_keys(model: type[BaseModel] = Config, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every leaf key of the configuration (``("mapping", "gppol", "ut", "kappa")``), through sections."""
    out: list[tuple[str, ...]] = []
    for name, field in model.model_fields.items():
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            out.extend(_config_keys(field.annotation, (*prefix, name)))
        else:
            out.append((*prefix, name))
    return out


CONFIG_KEYS = _config_keys()


def _config_text(path: tuple[str, ...], value: str, where: str) -> str:
    """Block YAML setting ``path`` to the raw scalar ``value`` (``where``: as the value, in a two-item list,
    as the key of the leaf's section, or as the key of the whole file)."""
    if where == "top-key":
        return f"? {value}\n: 1\n"
    lines = [f"{'  ' * depth}{key}:" for depth, key in enumerate(path[:-1])]
    indent = "  " * (len(path) - 1)
    if where == "key":
        lines += [f"{indent}? {value}", f"{indent}: 1"]
    elif where == "list":
        lines.append(f"{indent}{path[-1]}: [{value}, 1]")
    else:
        lines.append(f"{indent}{path[-1]}: {value}")
    return "\n".join(lines) + "\n"


@given(
    path=st.sampled_from(CONFIG_KEYS),
    value=YAML_ODD_SCALARS,
    where=st.sampled_from(["value", "value", "list", "key", "top-key"]),
)
def test_config_yaml_tags_and_implicit_types_read_cleanly(
    path: tuple[str, ...], value: str, where: str
) -> None:
    """Any key of any section set to a date, a timestamp, ``!!binary``, ``!!set``, a 5000-digit number or a
    tag YAML refuses (or such a scalar as a key): a Config or one ConfigError line, never ValueError."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg_path = Path(tmp) / "c.yaml"
        cfg_path.write_text(_config_text(path, value, where))
        reads_cleanly(lambda: load_config(cfg_path))


_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-100, 100).map(lambda v: f"{v:.3f}"),
    st.integers(-(2**70), 2**70).map(str),
    st.sampled_from(NASTY),
)
_STAMP = st.one_of(
    st.floats(-10, 1e4).map(lambda v: f"{v:.6f}"),
    st.decimals(allow_nan=False, allow_infinity=False, places=9).map(str),
    st.integers(-(2**64), 2**64).map(str),
    st.sampled_from(NASTY),
)


@st.composite
def _carmen_log(draw: st.DrawFn) -> str:
    """A generated log: mostly well-formed records whose stamps run in order, back, equal or far apart,
    and now and then one field drawn from anywhere (non-finite, huge, malformed)."""
    n_records = draw(st.integers(1, 12))
    stamp_mode = draw(st.sampled_from(["increasing", "jittered", "shuffled", "equal", "any"]))
    base = draw(st.sampled_from([0.0, 976052857.0, -5.0, 7.2e9]))
    lines = []
    for k in range(n_records):
        kind = draw(
            st.sampled_from(["FLASER", "FLASER", "RLASER", "ROBOTLASER1", "ODOM", "ODOM", "PARAM", "#"])
        )
        if stamp_mode == "increasing":
            stamp = f"{base + 0.1 * k:.6f}"
        elif stamp_mode == "jittered":
            stamp = f"{base + 0.1 * k + draw(st.floats(-2, 2)):.6f}"
        elif stamp_mode == "shuffled":
            stamp = f"{base + draw(st.floats(0, 50)):.6f}"
        elif stamp_mode == "equal":
            stamp = f"{base:.6f}"
        else:
            stamp = draw(_STAMP)
        n = draw(st.integers(1, 5))
        fields = {
            "ranges": [f"{draw(st.floats(0, 90)):.2f}" for _ in range(n)],
            "pose": [f"{draw(st.floats(-50, 50)):.3f}" for _ in range(6)],
            "settings": ["-1.570796", "3.141593", f"{draw(st.floats(-1, 1)):.6f}", "81.9", "0.01", "0"],
            "motion": ["0.0"] * 5,
        }
        if draw(st.integers(0, 7)) == 0:  # one field from anywhere
            group = draw(st.sampled_from(sorted(fields)))
            fields[group][draw(st.integers(0, len(fields[group]) - 1))] = draw(_NUMBER)
        count = draw(st.integers(-1, 6)) if draw(st.integers(0, 9)) == 0 else n
        ranges, pose = " ".join(fields["ranges"]), " ".join(fields["pose"])
        if kind in ("FLASER", "RLASER"):
            lines.append(f"{kind} {count} {ranges} {pose} {stamp} host {stamp}")
        elif kind == "ROBOTLASER1":
            settings, motion = " ".join(fields["settings"]), " ".join(fields["motion"])
            lines.append(f"ROBOTLASER1 0 {settings} {count} {ranges} 0 {pose} {motion} {stamp} host {stamp}")
        elif kind == "ODOM":
            lines.append(f"ODOM {pose} {stamp} host {stamp}")
        else:
            lines.append(f"{kind} name {stamp}")
    return "\n".join(lines) + "\n"


@given(
    text=_carmen_log(),
    name=st.sampled_from(["gen.clf", "gen.gfs.log", "gen-corrected.log"]),
    laser=st.sampled_from(["auto", "auto", "FLASER", "ROBOTLASER1"]),
    jitter_s=st.sampled_from([0.0, 1.0, 1.0, 1e6, 1e300]),
    range_min_m=st.sampled_from([0.0, 0.05, 0.05, 10.0]),
)
def test_generated_carmen_logs_read_cleanly(
    text: str, name: str, laser: str, jitter_s: float, range_min_m: float
) -> None:
    """Logs generated record by record: any stamps (ordered, equal, far apart), counts and values."""
    cfg = InputConfig(carmen_laser=laser, carmen_stamp_jitter_s=jitter_s, carmen_range_min_m=range_min_m)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_text(text)
        reads_cleanly(lambda: read_carmen(path, cfg))


@given(kf_ops=MUTATIONS, raw_ops=st.lists(_OP, max_size=2))
def test_keyframe_matching_reads_cleanly(kf_ops: list[tuple], raw_ops: list[tuple]) -> None:
    """Matching a mutated keyframe log against a (mutated) raw log: a result or a DatasetError."""
    raw_text = "\n".join(_flaser(10.0 + 0.2 * k, ranges=f"1.0 {k}.5 3.25 4.0") for k in range(6)) + "\n"
    kf_text = "\n".join(_flaser(10.0 + 0.4 * k, ranges=f"1.0 {2 * k}.5 3.25 4.0") for k in range(3)) + "\n"
    with tempfile.TemporaryDirectory() as tmp:
        raw_path, kf_path = Path(tmp) / "raw.clf", Path(tmp) / "kf.gfs.log"
        raw_path.write_bytes(mutate(raw_text.encode(), raw_ops))
        kf_path.write_bytes(mutate(kf_text.encode(), kf_ops))

        def match() -> object:
            result = match_keyframe_scans(read_carmen(kf_path), read_carmen(raw_path))
            matched = result.indices[result.indices >= 0]
            assert np.all(np.diff(matched) > 0)
            return result

        reads_cleanly(match)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# -------------------------------------------------------------------------------------- the corpus


def _corpus_cases() -> list[Path]:
    return sorted(TEXT_CORPUS.iterdir()) if TEXT_CORPUS.is_dir() else []


@pytest.mark.parametrize("path", _corpus_cases(), ids=lambda p: p.name)
def test_corpus_reads_cleanly(path: Path) -> None:
    """Every crash the fuzzing found (and each defect of issue 15), replayed: ``<reader>-<what>.<ext>``."""
    reader = READERS[path.name.split("-", 1)[0]]
    reads_cleanly(lambda: reader(path))
