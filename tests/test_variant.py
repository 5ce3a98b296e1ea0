"""Variant selection: JIT variants only, with messages that say what to do."""

import pytest

from mi_lidar._variant import find_llvm, require_jit_variant, select_variant
from mi_lidar.core.errors import SetupError
from mi_lidar.core.sensor_model import CHANNELS


class FakeMitsuba:
    def __init__(self, current):
        self.current = current

    def variant(self):
        return self.current

    def variants(self):
        return ["scalar_rgb", "llvm_ad_rgb"]

    def set_variant(self, name):
        self.current = name


def test_scalar_variant_request_is_refused(monkeypatch):
    monkeypatch.setenv("MI_LIDAR_VARIANT", "scalar_rgb")
    with pytest.raises(SetupError, match="needs a JIT variant"):
        select_variant(FakeMitsuba(None))


def test_unknown_variant_lists_choices(monkeypatch):
    monkeypatch.setenv("MI_LIDAR_VARIANT", "cuda_ad_nope")
    with pytest.raises(SetupError, match="llvm_ad_rgb"):
        select_variant(FakeMitsuba(None))


def test_existing_jit_variant_is_kept(monkeypatch):
    monkeypatch.delenv("MI_LIDAR_VARIANT", raising=False)
    assert select_variant(FakeMitsuba("llvm_ad_rgb")) == "llvm_ad_rgb"
    assert select_variant(FakeMitsuba(None)) == "llvm_ad_rgb"


def test_plugins_refuse_a_scalar_variant():
    with pytest.raises(SetupError, match="mi.set_variant"):
        require_jit_variant(FakeMitsuba("scalar_rgb"))


def test_llvm_found_on_this_machine():
    path = find_llvm()
    assert path is not None and "LLVM" in path


def test_plugins_are_registered_again_after_a_variant_change():
    import mitsuba as mi

    import mi_lidar  # noqa: F401

    mi.set_variant("llvm_ad_mono")
    try:
        scene = mi.load_dict(
            {
                "type": "scene",
                "sensor": {"type": "lidar", "pattern": "planar-180"},
                "integrator": {"type": "lidar_integrator"},
                "ball": {"type": "sphere", "bsdf": {"type": "lidar_material", "p_hit": 1.0}},
            }
        )
        image = mi.render(scene)
        assert image.shape == (180, 1, len(CHANNELS))
    finally:
        mi.set_variant("llvm_ad_rgb")
