"""Shared helpers for the DACR core tests: hypothesis strategies and independent references.

The reference implementations here deliberately do NOT call dacr_learn: they are written
from the formulas of docs/design.md §1/§2 in numpy / plain Python (joint lengths from the
constant-curvature geometry, the classic Rz(θ)Ry(φ)Rz(−θ) arc, a rigid-link URDF chain for
pytorch_kinematics), so that a test compares our code against something that was derived
separately. Test modules import them with ``from conftest import ...``.
"""
from __future__ import annotations

import importlib.util
import math
import os
import pickle
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]

# Intra-op threads for the whole suite. `make test` runs the suite with 1 thread, then the reduction_order
# tests (tests/reduction_order.py) with 2 threads (DACR_TEST_THREADS=2) and portable kernels: another float
# reduction order, so a test that only passes bit for bit on one machine fails here first.
TEST_THREADS = int(os.environ.get("DACR_TEST_THREADS", "1"))
torch.set_num_threads(TEST_THREADS)


def _cache_export_schema_hints() -> None:
    """torch.export.load (every exported program the tests load back: 0.1–1 s each) rebuilds the program's schema
    dataclasses from JSON and asks ``typing.get_type_hints`` for the same few schema classes tens of thousands of
    times per file: a third of the load. In the test processes those answers are cached from the first load on
    (they depend on the class only, the schema module being fixed); the loaded programs are the same. Nothing is
    changed if torch's deserializer is not as expected."""
    import functools
    import types
    import typing

    load = torch.export.load

    @functools.wraps(load)
    def first_load(*args, **kwargs):
        torch.export.load = load                          # from now on torch's own, with the cache below
        try:
            from torch._export.serde import serialize
            schema = vars(serialize.schema)
        except (ImportError, AttributeError):
            return load(*args, **kwargs)
        if getattr(serialize, "typing", None) is typing:
            hints = functools.lru_cache(maxsize=None)(lambda cls: typing.get_type_hints(cls, globalns=schema))

            def get_type_hints(obj, globalns=None, localns=None, include_extras=False):
                if globalns is schema and localns is None and not include_extras:
                    return hints(obj)
                return typing.get_type_hints(obj, globalns, localns, include_extras)

            proxy = types.ModuleType("typing")
            proxy.__dict__.update(vars(typing))
            proxy.get_type_hints = get_type_hints
            serialize.typing = proxy
        return load(*args, **kwargs)

    torch.export.load = first_load


_cache_export_schema_hints()


# Hypothesis: derandomised under CI (CI=true) or DACR_HYPOTHESIS_PROFILE=ci, so a CI run is
# reproducible; the default profile draws new examples each run and prints a failure's blob.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev", print_blob=True)
settings.load_profile(os.environ.get("DACR_HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))


def assert_tree_close(actual, expected, *, atol: float, rtol: float = 0.0, path: str = "") -> None:
    """Assert two nested dicts/lists/tuples are equal in structure, keys, strings, ints and bools, and
    their floats agree within ``atol + rtol·|expected|``; the message names the first differing path."""
    where = path or "<root>"
    if isinstance(expected, dict):
        assert isinstance(actual, dict) and actual.keys() == expected.keys(), f"{where}: keys differ"
        for k in expected:
            assert_tree_close(actual[k], expected[k], atol=atol, rtol=rtol, path=f"{path}.{k}")
    elif isinstance(expected, (list, tuple)):
        assert isinstance(actual, (list, tuple)) and len(actual) == len(expected), f"{where}: lengths differ"
        for i, (a, e) in enumerate(zip(actual, expected, strict=True)):
            assert_tree_close(a, e, atol=atol, rtol=rtol, path=f"{path}[{i}]")
    elif isinstance(expected, float) or isinstance(actual, float):
        assert isinstance(actual, (int, float)) and not isinstance(actual, bool), f"{where}: {actual!r} is no number"
        assert abs(actual - expected) <= atol + rtol * abs(expected), f"{where}: {actual!r} vs {expected!r}"
    else:
        assert actual == expected, f"{where}: {actual!r} != {expected!r}"


def roundoff_tol(dtype: torch.dtype, scale: float = 1.0, ulps: float = 64.0) -> float:
    """Absolute tolerance for two results that differ only by rounding: ``ulps`` machine epsilons of
    ``dtype`` at magnitude ``scale``.

    Mathematically equal computations done in another order (batched vs per sample, another BLAS
    kernel, CPU or thread count) differ by about one rounding per operation; the default 64 covers the
    short operation chains compared with it here (a linear solve is given more, ``ulps=1024``).
    """
    return float(ulps * torch.finfo(dtype).eps * scale)
ROBOT_CONFIGS = sorted((ROOT / "configs" / "robots").glob("*.yaml"))
TYPE1 = ROOT / "configs" / "robots" / "type1.yaml"

# Modest, deterministic-per-run hypothesis budget: the whole core suite must stay fast on 2 cores.
FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# --------------------------------------------------------------------------------------------
# Strategies: robot description dicts (valid by construction, well conditioned)
# --------------------------------------------------------------------------------------------


@st.composite
def segment_dicts(draw, seg_type: str | None = None, layout: str | None = None, unequal: bool | None = None):
    """A valid, well-conditioned segment dict of the YAML schema (docs/design.md §4)."""
    seg_type = seg_type or draw(st.sampled_from(["0", "I", "II", "III"]))
    length = draw(st.floats(0.05, 0.2))
    radius = draw(st.floats(0.004, 0.015))
    n = draw(st.integers(3, 7))
    layout = layout or draw(st.sampled_from(["symmetric", "arbitrary"]))
    d: dict = {"type": seg_type, "length": length, "radius": radius}
    if layout == "symmetric":
        d["joints"] = n
        d["offset"] = draw(st.floats(-math.pi, math.pi))
    else:
        # Spread around the backbone (jitter ≤ 35 % of the spacing): full rank, well conditioned.
        offset = draw(st.floats(-math.pi, math.pi))
        jitter = draw(st.lists(st.floats(-0.35, 0.35), min_size=n, max_size=n))
        d["joint_angles"] = [offset + 2 * math.pi * (i + jitter[i]) / n for i in range(n)]
        twists = seg_type in ("II", "III")
        if unequal is None:
            unequal = draw(st.booleans())
        if twists:
            # Twisting segments need equal joint radii, but they may differ from the reference radius.
            d["joint_radii"] = [radius * draw(st.floats(0.7, 1.3))] * n
        elif unequal:
            d["joint_radii"] = [radius * draw(st.floats(0.6, 1.4)) for _ in range(n)]
    limits: dict = {"bend": draw(st.floats(0.3, 2.5))}
    if seg_type in ("I", "III"):
        limits["length"] = [0.8 * length, 1.2 * length]
    if seg_type in ("II", "III"):
        limits["twist"] = [-1.2, 1.2]
    d["limits"] = limits
    return d


@st.composite
def robot_dicts(draw, max_segments: int = 3, types=("0", "I", "II", "III"), routing: str | None = None):
    """A valid robot dict; coupled robots only twist in their last segment (docs/design.md §1)."""
    m = draw(st.integers(1, max_segments))
    routing = routing or draw(st.sampled_from(["independent", "coupled"]))
    segs = []
    for j in range(m):
        allowed = [t for t in types if routing == "independent" or j == m - 1 or t in ("0", "I")]
        segs.append(draw(segment_dicts(seg_type=draw(st.sampled_from(allowed)))))
    return {"name": "hyp-robot", "routing": routing, "segments": segs}


def robots(**kw):
    """Strategy of RobotSpec built from :func:`robot_dicts`."""
    return robot_dicts(**kw).map(RobotSpec.from_dict)


seeds = st.integers(0, 2**31 - 1)       # a generator seed


# --------------------------------------------------------------------------------------------
# Random features within the robot's limits
# --------------------------------------------------------------------------------------------


def random_features(spec: RobotSpec, batch: tuple[int, ...], seed: int, dtype=torch.float64,
                    bend_scale: float = 1.0, straight: bool = False) -> torch.Tensor:
    """Features (*batch, m, 4) with |u| ≤ bend, β and α uniform in their ranges.

    Non-actuated columns already hold their fixed values (β = l, α = 0), so the encoder must
    return exactly this tensor. ``straight=True`` sets ρ = 0.
    """
    g = torch.Generator().manual_seed(seed)
    cols = []
    for seg in spec.segments:
        r = torch.rand(*batch, 4, generator=g, dtype=torch.float64)
        phi = 0.0 if straight else bend_scale * seg.bend * torch.sqrt(r[..., 0])
        theta = 2 * math.pi * r[..., 1]
        lo, hi = seg.length_range or (seg.length, seg.length)
        tlo, thi = seg.twist_range or (0.0, 0.0)
        cols.append(torch.stack([seg.radius * phi * torch.cos(theta), seg.radius * phi * torch.sin(theta),
                                 lo + (hi - lo) * r[..., 2], tlo + (thi - tlo) * r[..., 3]], dim=-1))
    return torch.stack(cols, dim=-2).to(dtype)


# --------------------------------------------------------------------------------------------
# Independent references (numpy, from the geometry; no dacr_learn code)
# --------------------------------------------------------------------------------------------


def reference_joint_vector(spec: RobotSpec, features: np.ndarray) -> np.ndarray:
    """Joint vector from the geometry of docs/design.md §1, one sample: features (m, 4) → (num_joints,).

    Joint i of segment j at (d_i, ψ_i) runs along every segment k it passes (k = j for
    independent routing, k ≤ j for coupled). Along segment k it has the helix length
    sqrt((α_k d_i)² + β_k²) minus its bending displacement, which for a constant-curvature arc
    with bending angle φ_k = ‖ρ⁽ᵏ⁾‖/d_k in direction θ_k is d_i·φ_k·cos(θ_k − ψ_i).
    """
    q = []
    for j, seg in enumerate(spec.segments):
        passed = range(j + 1) if spec.routing == "coupled" else (j,)
        for psi, di in zip(seg.joint_angles, seg.joint_radii, strict=True):
            total = 0.0
            for k in passed:
                sk = spec.segments[k]
                rho_re, rho_im, beta, alpha = features[k]
                beta = beta if sk.extends else sk.length
                alpha = alpha if sk.twists else 0.0
                phi, theta = math.hypot(rho_re, rho_im) / sk.radius, math.atan2(rho_im, rho_re)
                total += math.sqrt((alpha * di) ** 2 + beta**2) - di * phi * math.cos(theta - psi)
            q.append(total)
    q += [features[k][3] for k, s in enumerate(spec.segments) if s.twists]
    return np.array(q)


def reference_actuated_matrix(spec: RobotSpec) -> np.ndarray:
    """W with q_lengths = W·w + q₀ for w = (ρ_re¹, ρ_im¹, …, ρ_reᵐ, ρ_imᵐ, h of each extending segment)."""
    rows = []
    ext = [k for k, s in enumerate(spec.segments) if s.extends]
    for j, seg in enumerate(spec.segments):
        passed = set(range(j + 1)) if spec.routing == "coupled" else {j}
        for psi, di in zip(seg.joint_angles, seg.joint_radii, strict=True):
            row = np.zeros(2 * spec.num_segments + len(ext))
            for k in passed:
                dk = spec.segments[k].radius
                row[2 * k:2 * k + 2] = [-di / dk * math.cos(psi), -di / dk * math.sin(psi)]
            for c, k in enumerate(ext):
                row[2 * spec.num_segments + c] = 1.0 if k in passed else 0.0
            rows.append(row)
    return np.array(rows)


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def classic_arc(theta: float, phi: float, beta: float) -> np.ndarray:
    """Webster & Jones arc: R = Rz(θ)Ry(φ)Rz(−θ), p = (β/φ)(cosθ(1−cosφ), sinθ(1−cosφ), sinφ). (4, 4)."""
    t = np.eye(4)
    t[:3, :3] = rot_z(theta) @ rot_y(phi) @ rot_z(-theta)
    if phi == 0.0:
        t[:3, 3] = [0.0, 0.0, beta]
    else:
        one_minus_cos = 2 * math.sin(phi / 2) ** 2       # = 1 − cos φ without cancellation near φ = 0
        t[:3, 3] = beta / phi * np.array([math.cos(theta) * one_minus_cos,
                                          math.sin(theta) * one_minus_cos, math.sin(phi)])
    return t


def arc_parameters(spec: RobotSpec, features: np.ndarray, k: int) -> tuple[float, float, float, float]:
    """(θ, φ, β, α) of segment k from one sample's features (m, 4), non-actuated values fixed."""
    seg = spec.segments[k]
    rho_re, rho_im, beta, alpha = features[k]
    return (math.atan2(rho_im, rho_re), math.hypot(rho_re, rho_im) / seg.radius,
            beta if seg.extends else seg.length, alpha if seg.twists else 0.0)


def reference_backbone(spec: RobotSpec, features: np.ndarray, per_segment: int) -> np.ndarray:
    """Backbone points (1 + m·K, 3) of one sample (m, 4) by the classic arc formula: the point s = j/K along
    segment k is the tip of the arc of bending angle s·φ and length s·β, after the full segments before it."""
    base, points = np.eye(4), [np.zeros(3)]
    for k in range(spec.num_segments):
        theta, phi, beta, alpha = arc_parameters(spec, features, k)
        roll = np.eye(4)
        roll[:3, :3] = rot_z(alpha)
        for j in range(1, per_segment + 1):
            s = j / per_segment
            points.append((base @ roll @ classic_arc(theta, s * phi, s * beta))[:3, 3])
        base = base @ roll @ classic_arc(theta, phi, beta)
    return np.array(points)


def classic_forward_kinematics(spec: RobotSpec, features: np.ndarray) -> np.ndarray:
    """Tip pose T⁽¹⁾…T⁽ᵐ⁾ with T⁽ʲ⁾ = Rz(α)·arc, one sample: (m, 4) → (4, 4)."""
    tip = np.eye(4)
    for k in range(spec.num_segments):
        theta, phi, beta, alpha = arc_parameters(spec, features, k)
        roll = np.eye(4)
        roll[:3, :3] = rot_z(alpha)
        tip = tip @ roll @ classic_arc(theta, phi, beta)
    return tip


# --------------------------------------------------------------------------------------------
# Rigid-link chain equivalent to the CC robot, for pytorch_kinematics
# --------------------------------------------------------------------------------------------

_LIMIT = '<limit lower="-100" upper="100" effort="1" velocity="1"/>'


def urdf_chain_string(twists: list[bool]) -> str:
    """URDF of m rigid-link blocks; block k: [rz α], rz θ, ry φ/2, prismatic z chord, ry φ/2, rz −θ."""
    axes = {"rz": ("revolute", "0 0 1"), "ry": ("revolute", "0 1 0"), "pz": ("prismatic", "0 0 1")}
    kinds = []
    for tw in twists:
        kinds += (["rz"] if tw else []) + ["rz", "ry", "pz", "ry", "rz"]
    links = "".join(f'<link name="link{i}"/>' for i in range(len(kinds) + 1))
    joints = "".join(
        f'<joint name="j{i}" type="{axes[k][0]}"><parent link="link{i}"/><child link="link{i + 1}"/>'
        f'<origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="{axes[k][1]}"/>{_LIMIT}</joint>'
        for i, k in enumerate(kinds))
    return f'<robot name="cc_equivalent">{links}{joints}</robot>'


def urdf_end_link(twists: list[bool]) -> str:
    return f"link{sum(5 + tw for tw in twists)}"


def chain_joint_values(theta, phi, beta, alpha, twist: bool):
    """Joint values of one block (torch or numpy arrays, broadcast): list of 5 or 6 arrays."""
    lib = torch if isinstance(phi, torch.Tensor) else np
    chord = beta * lib.sinc(phi / (2 * math.pi))          # 2β·sin(φ/2)/φ, = β at φ = 0
    vals = [theta, phi / 2, chord, phi / 2, -theta]
    return ([alpha] if twist else []) + vals


# A robot with both twisting types (II then III), used by the export and control tests.
TWISTING = {"name": "twisting", "routing": "independent", "segments": [
    {"type": "II", "length": 0.1, "radius": 0.008, "joints": 4, "limits": {"bend": 1.2, "twist": [-1.0, 1.0]}},
    {"type": "III", "length": 0.08, "radius": 0.007, "joints": 3, "offset": 0.3,
     "limits": {"bend": 1.0, "length": [0.07, 0.09], "twist": [-0.5, 0.5]}}]}


def spec_by_name(name: str) -> RobotSpec:
    """configs/robots/<name>.yaml, or the TWISTING robot for name == "twisting"."""
    return RobotSpec.from_dict(TWISTING) if name == "twisting" else RobotSpec.from_yaml(
        ROOT / "configs" / "robots" / f"{name}.yaml")


TDCR3_YAML = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
TDCR3 = RobotSpec.from_yaml(TDCR3_YAML)


def max_diff(a, b) -> float:
    """Largest absolute difference of two tensors, compared in float64."""
    return (a.double() - b.double()).abs().max().item()


def autograd_jacobians(model: torch.nn.Module, spec: RobotSpec, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference Jacobians (J_f, J_q) of one sample by torch.func.jacrev of q ↦ FK(q) and f ↦ FK(dec(f))
    (``model``: an FKModel of ``spec``)."""
    from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
    from dacr_learn.lie import twist_jacobian
    from dacr_learn.models import actuated_selection

    enc, dec, sel = ClarkeEncoder(spec).double(), ClarkeDecoder(spec).double(), actuated_selection(spec).double()
    base = torch.tensor([[0.0, 0.0, 0.0 if s.extends else s.length, 0.0] for s in spec.segments],
                        dtype=torch.float64).flatten()
    pose = model(q[None])[0]
    jac_q = twist_jacobian(pose, torch.func.jacrev(lambda x: model(x[None])[0])(q))
    f = enc(q).flatten() @ sel.mT
    decode = lambda x: dec((base + x @ sel).unflatten(-1, (spec.num_segments, 4)))  # noqa: E731
    jac_f = twist_jacobian(pose, torch.func.jacrev(lambda x: model(decode(x)[None])[0])(f))
    return jac_f, jac_q


@pytest.fixture(scope="session")
def labelled_robot_dir(tmp_path_factory) -> tuple[Path, Path]:
    """(data folder with train.csv only, robot YAML with its servo map next to it): a labelled synthetic
    recording (hardware_testkit.write_labelled_robot), shared read-only by the hardware selection tests."""
    from hardware_testkit import write_labelled_robot

    return write_labelled_robot(tmp_path_factory.mktemp("labelled"))


@pytest.fixture(scope="module")
def v4_spec() -> RobotSpec:
    """FTDCR v4's nominal robot (configs/robots/ftdcr_v4.yaml)."""
    from hardware_testkit import V4_ROBOT

    return RobotSpec.from_yaml(V4_ROBOT)


@pytest.fixture(scope="module")
def v4_pulls(v4_spec):
    """FTDCR v4's single-tendon pulls (data/ftdcr_v4/tendon_pull.csv) with the nominal robot."""
    from hardware_testkit import V4_DATA

    from dacr_learn.hardware.recording import load_recording

    return load_recording(V4_DATA / "tendon_pull.csv", v4_spec)


@pytest.fixture(scope="module")
def v4_train_head(tmp_path_factory):
    """(spec, servo map, the first 240 rows of FTDCR v4's train.csv) of the calibrated robot."""
    from hardware_testkit import load_v4_train_head

    return load_v4_train_head(tmp_path_factory.mktemp("v4_train_head"))


@pytest.fixture(scope="session")
def v4_slice(tmp_path_factory):
    """The benchmark setup of every 8th row of FTDCR v4's train.csv (hardware_testkit.load_v4_slice), shared
    read-only by the compositional hardware model's deploy tests. Sets torch to one thread."""
    from hardware_testkit import load_v4_slice

    root = tmp_path_factory.mktemp("v4_slice")
    torch.set_num_threads(1)
    return load_v4_slice(root)


@pytest.fixture(scope="session")
def compositional_models(v4_slice):
    """config → an ensemble of 2 CCCompositionalResidual members of v4_slice trained for 20 steps, for each of
    hardware_testkit.COMPOSITIONAL_CONFIGS (no context; distal with torsion; segment): shared read-only."""
    from hardware_testkit import COMPOSITIONAL_CONFIGS, compositional_ensemble

    return {config: compositional_ensemble(v4_slice, config) for config in COMPOSITIONAL_CONFIGS}


# `make test` names one folder per process (DACR_TEST_EXPORTS) that its first and second pass share.
SHARED_EXPORTS = Path(os.environ["DACR_TEST_EXPORTS"]).resolve() if os.environ.get("DACR_TEST_EXPORTS") else None


def first_pass_export(name: str, make, tmp_path_factory) -> tuple[Path, dict]:
    """(folder, record): ``make(folder)`` writes an export (and the checkpoint it was made from) into the empty
    ``folder`` and returns a record of it (its metadata, the warnings it raised: a dict that pickles). Under
    `make test` the folder is ``DACR_TEST_EXPORTS/name``, and the second pass (two threads, portable kernels) finds
    the first pass's export there: it runs the programs exported in the first pass, as a deployment runs an export
    made on another machine, against its own eager results instead of tracing them again (torch.export takes
    seconds to tens of seconds per model). Elsewhere: a fresh temporary folder."""
    if SHARED_EXPORTS is None:
        folder = tmp_path_factory.mktemp(name)
        return folder, make(folder)
    folder, done = SHARED_EXPORTS / name, SHARED_EXPORTS / name / "record.pickle"
    if done.is_file():                                   # written by this make test's first pass, a moment ago
        return folder, pickle.loads(done.read_bytes())
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    record = make(folder)
    done.write_bytes(pickle.dumps(record))
    return folder, record


@pytest.fixture(scope="session")
def history_export(tmp_path_factory):
    """The 2-member history test model as --save writes it (hardware_testkit.saved_history_model), exported once for
    the session without AOTI (an export takes seconds; :func:`first_pass_export`): (model, checkpoint, export folder,
    metadata, commands [mm], the messages of the warnings the export raised). Shared read-only by the export and
    control tests."""
    from hardware_testkit import export_recording_warnings, saved_history_model

    from dacr_learn.hardware.deploy.checkpoint import load_hardware_model

    def make(root: Path) -> dict:
        _, ckpt, commands = saved_history_model(root, members=2)
        meta, caught = export_recording_warnings(ckpt, root / "export")
        return {"meta": meta, "caught": caught, "commands": commands}

    root, record = first_pass_export("history_export", make, tmp_path_factory)
    ckpt = root / "model.pt"
    return load_hardware_model(ckpt), ckpt, root / "export", record["meta"], record["commands"], record["caught"]


def save_small_checkpoint(module, path: Path) -> None:
    """Save ``module`` (a Lightning module of dacr_learn.training, weights as they are) as a checkpoint at ``path``,
    its normalisation fitted to 2,048 samples of its robot (seed 0): what the exporters load."""
    import lightning

    from dacr_learn.data import generate

    data = generate(module.spec, 2048, seed=0)
    module.model.fit_normalization(data["q"], data["pose"])
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": lightning.__version__}, path)


@pytest.fixture(scope="session")
def jacobian_aoti_package(tmp_path_factory) -> Path:
    """The export folder (``fk.ckpt`` beside it) of a small FK model of the 3-segment coupled robot (2×16, random
    weights, normalisation fitted to 2 048 samples) with the AOTInductor package of its jacobian (autotune off; its
    fk only as a torch.export program). One AOTInductor build, shared read-only by the C++ tests and the export's."""
    from dacr_learn import export as dexport
    from dacr_learn.training import FKModule

    d = tmp_path_factory.mktemp("aoti_package")
    torch.manual_seed(0)
    save_small_checkpoint(FKModule(robot=str(TDCR3_YAML), width=16, depth=2), d / "fk.ckpt")
    dexport.export_checkpoint(d / "fk.ckpt", d / "fk", aoti=("jacobian",))
    return d / "fk"


@pytest.fixture(scope="module")
def compositional_split():
    """(frozen calibrated CC model, synthetic split of 64 rows) of the labelled synthetic robot
    (hardware_testkit.synthetic_compositional_split)."""
    from hardware_testkit import synthetic_compositional_split

    return synthetic_compositional_split()


@pytest.fixture()
def one_thread():
    """The suite's thread count (``DACR_TEST_THREADS``, default 1), restored after the test."""
    threads = torch.get_num_threads()
    torch.set_num_threads(TEST_THREADS)
    yield
    torch.set_num_threads(threads)


@pytest.hookimpl(tryfirst=True)        # before -k / -m deselect: every collected module is checked
def pytest_collection_modifyitems(config, items):
    """Mark the tests of tests/reduction_order.py ``reduction_order`` (and ``second_pass_beside_slow`` in the
    modules of its BESIDE_THE_SLOW_TESTS); a listed name missing from its collected
    module is an error (a renamed test must not drop out of `make test`'s second pass unnoticed)."""
    from reduction_order import BESIDE_THE_SLOW_TESTS, REDUCTION_ORDER

    modules = {}
    for item in items:
        module = item.module.__name__ + ".py" if getattr(item, "module", None) else None
        modules[module] = item.module if module else None
        if item.originalname in REDUCTION_ORDER.get(module, ()):
            item.add_marker(pytest.mark.reduction_order)
            if module in BESIDE_THE_SLOW_TESTS:
                item.add_marker(pytest.mark.second_pass_beside_slow)
    stale = [f"{m}::{name}" for m, mod in modules.items() if m in REDUCTION_ORDER
             for name in REDUCTION_ORDER[m] if not hasattr(mod, name)]
    stale += [f"{m} (BESIDE_THE_SLOW_TESTS)" for m in BESIDE_THE_SLOW_TESTS if m not in REDUCTION_ORDER]
    if stale:
        raise pytest.UsageError(f"tests/reduction_order.py lists tests that do not exist: {stale}")


def pytest_report_header(config):
    from hypothesis import settings as current

    return (f"dacr_learn tests: torch threads {TEST_THREADS} (DACR_TEST_THREADS), hypothesis profile "
            f"{current._current_profile!r} (derandomize={current.default.derandomize})")


def write_run_config(tmp_path: Path, task: str = "FKModule", robot: str = "configs/robots/type1.yaml", epochs: int = 3,
                     run_name: str = "smoke", callbacks: list[dict] | None = None, **data) -> Path:
    """A small train.py config (a 2×32 MLP, 2 000 samples, runs under ``tmp_path/runs``) written to
    ``tmp_path/config.yaml``; ``data`` entries override the datamodule's arguments."""
    trainer = {"accelerator": "cpu", "devices": 1, "max_epochs": epochs, "enable_progress_bar": False,
               "log_every_n_steps": 5, "enable_model_summary": False}
    if callbacks:
        trainer["callbacks"] = callbacks
    cfg = {"run_name": run_name, "runs_dir": str(tmp_path / "runs"), "seed_everything": 0, "trainer": trainer,
           "model": {"class_path": f"dacr_learn.training.{task}", "init_args": {"width": 32, "depth": 2, "lr": 1e-2}},
           "data": {"robot": str(ROOT / robot), "n_train": 2000, "n_val": 256, "n_test": 300, "batch_size": 64,
                    **data}}
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def no_ablation_reports(rows, out: Path, robots_order=None, title: str = "") -> dict:
    """Stands in for dacr_learn.cli.ablation's write_reports (monkeypatched) in tests that check a grid's rows only:
    the PNGs and the Rerun recording take seconds of CPU per call (test_ablation.py's quick grid test checks them)."""
    return {"summary": out / "summary.md", "plots": [], "rrd": out / "ablation.rrd"}


def readme_sections() -> dict[str, str]:
    """The README's ``## `` sections: heading text → the section's text (heading line included)."""
    sections, name, lines = {}, "", []
    for line in (ROOT / "README.md").read_text(encoding="utf-8").splitlines(keepends=True):
        if line.startswith("## "):
            sections[name] = "".join(lines)
            name, lines = line[3:].strip(), []
        lines.append(line)
    sections[name] = "".join(lines)
    return sections


# --------------------------------------------------------------------------------------------
# Users' broken files: the error names the file (tests of the loaders' refusals)
# --------------------------------------------------------------------------------------------


def names(path: Path, *parts: str) -> str:
    """Regex that the message starts with the file and contains every part, in order."""
    return "^" + ".*".join(re.escape(p) for p in (str(path), *parts))


def truncated(path: Path, keep: int) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[:keep] if keep >= 0 else data[:len(data) + keep])
    return path


# --------------------------------------------------------------------------------------------
# Examples and a small trained model
# --------------------------------------------------------------------------------------------


def load_example(name: str, folder: str = "examples"):
    """<folder>/<name>.py (examples/ or benchmarks/) imported as module ``name`` (registered in sys.modules: its
    dataclasses look it up)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def learned_jacobian(tmp_path_factory):
    """A small FK model of the type-1 robot trained for a few seconds, exported (torch.export program) and loaded
    (test_control.py and the tracking example's test)."""
    import lightning.pytorch as pl

    from dacr_learn import export as dexport
    from dacr_learn.datamodule import KinematicsDataModule
    from dacr_learn.training import FKModule

    d = tmp_path_factory.mktemp("learned")
    torch.manual_seed(0)
    module = FKModule(robot=str(TYPE1), width=32, depth=2, lr=1e-2, rot_weight=0.1)
    dm = KinematicsDataModule(robot=str(TYPE1), n_train=6000, n_val=200, n_test=200, batch_size=256)
    trainer = pl.Trainer(max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu", devices=1)
    trainer.fit(module, datamodule=dm)
    trainer.save_checkpoint(d / "fk.ckpt")
    dexport.export_checkpoint(d / "fk.ckpt", d / "export", aoti=False)
    jacobian = dexport.load(d / "export", "jacobian")
    jacobian.run_dir = d                    # for the example test: checkpoint and export live here
    return jacobian
