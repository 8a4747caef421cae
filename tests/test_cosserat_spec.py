"""The optional ``mechanics:`` block of a robot description and the routing the Cosserat model accepts."""
from __future__ import annotations

import math
import re

import pytest
import torch
from conftest import ROOT

from dacr_learn.cosserat.tendon import tendon_routing
from dacr_learn.robot import MechanicsSpec, RobotSpec

BASE = {"name": "r", "segments": [{"type": "I", "length": 0.1, "radius": 0.008, "joints": 4}]}
MECH = {"youngs_modulus": 6.0e10, "poisson_ratio": 0.33, "outer_radius": 0.0005, "inner_radius": 0.0002,
        "density": 6450.0, "tendon_compliance": 2.5e-5}


def test_existing_robot_files_have_no_mechanics_and_still_load():
    for path in sorted((ROOT / "configs" / "robots").glob("*.yaml")):
        spec = RobotSpec.from_yaml(path)
        assert (spec.mechanics is not None) == (path.name == "tdcr_3seg_cosserat.yaml")
        assert "mechanics" in spec.to_dict() or spec.mechanics is None


def test_mechanics_round_trips_through_dict_and_yaml(tmp_path):
    for mech in (MECH, {"youngs_modulus": 2.0e11, "shear_modulus": 7.9e10, "outer_radius": 0.0008}):
        spec = RobotSpec.from_dict(BASE | {"mechanics": mech})
        assert RobotSpec.from_dict(spec.to_dict()) == spec
        spec.to_yaml(tmp_path / "r.yaml")
        assert RobotSpec.from_yaml(tmp_path / "r.yaml") == spec
    m = RobotSpec.from_dict(BASE | {"mechanics": MECH}).mechanics
    assert math.isclose(m.shear_modulus, 6.0e10 / (2 * 1.33), rel_tol=1e-15) and m.poisson_ratio == 0.33
    defaults = MechanicsSpec.from_dict({"youngs_modulus": 1e9, "poisson_ratio": 0.5, "outer_radius": 1e-3})
    assert (defaults.inner_radius, defaults.density, defaults.tendon_compliance) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("change,field", [
    ({"youngs_modulus": -1.0}, "mechanics.youngs_modulus"),
    ({"youngs_modulus": "6.0e10"}, "mechanics.youngs_modulus"),         # PyYAML reads 6.0e10 as a string
    ({"poisson_ratio": 0.6}, "mechanics.poisson_ratio"),
    ({"shear_modulus": 2e10}, "mechanics: got ['poisson_ratio', 'shear_modulus']"),
    ({"poisson_ratio": None}, "mechanics.poisson_ratio"),
    ({"outer_radius": 0.0}, "mechanics.outer_radius"),
    ({"inner_radius": 0.0005}, "mechanics.inner_radius"),
    ({"density": -1.0}, "mechanics.density"),
    ({"tendon_compliance": math.inf}, "mechanics.tendon_compliance"),
    ({"stiffness": 1.0}, "mechanics: got ['stiffness']"),
])
def test_bad_mechanics_name_the_field_and_the_expectation(change, field):
    with pytest.raises(ValueError, match=re.escape(field) + ".*expected"):
        RobotSpec.from_dict(BASE | {"mechanics": MECH | change})


def test_missing_modulus_pair_is_rejected():
    mech = {k: v for k, v in MECH.items() if k != "poisson_ratio"}
    with pytest.raises(ValueError, match="exactly one of shear_modulus"):
        RobotSpec.from_dict(BASE | {"mechanics": mech})


def test_routing_geometry_and_refused_robots():
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / "tdcr_3seg_cosserat.yaml")
    routing = tendon_routing(spec)
    angles = torch.tensor([a for s in spec.segments for a in s.joint_angles], dtype=torch.float64)
    assert torch.allclose(torch.atan2(routing.offsets[:, 1], routing.offsets[:, 0]).remainder(2 * math.pi),
                          angles.remainder(2 * math.pi), atol=1e-15)
    assert routing.segment.tolist() == [0] * 4 + [1] * 4 + [2] * 4
    assert routing.active(1).tolist() == list(range(4, 12)) and routing.terminating(2).tolist() == [8, 9, 10, 11]
    assert torch.allclose(routing.ends, torch.tensor([0.0, 0.10, 0.19, 0.27], dtype=torch.float64), atol=1e-15)
    independent = spec.to_dict() | {"routing": "independent"}
    with pytest.raises(ValueError, match="routing"):
        tendon_routing(RobotSpec.from_dict(independent))
    twisting = BASE | {"segments": [{"type": "III", "length": 0.1, "radius": 0.008, "joints": 4}]}
    with pytest.raises(ValueError, match=r"segments\[0\]\.type"):
        tendon_routing(RobotSpec.from_dict(twisting))
