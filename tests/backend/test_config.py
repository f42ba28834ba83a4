"""The engine's one typed config: the paper's defaults, TOML, --set, unknown keys."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from backend.config import ConfigError, EngineConfig, apply_override


def test_defaults_are_the_papers_but_the_box_distance():
    c = EngineConfig()
    assert (c.sync.max_span, c.sync.max_std) == (0.05, 0.025)
    assert c.preprocess.min_confidence == 0.6 and c.preprocess.max_persons == 10
    # not the paper's 100 px at 848x480 (0.1 of the diagonal): 29 px, measured in crowded rooms
    assert c.preprocess.min_box_distance * (848**2 + 480**2) ** 0.5 == pytest.approx(29, abs=1)
    a = c.associate
    assert (a.min_height, a.max_height, a.max_distance, a.min_views) == (1.70, 2.00, 1.0, 2)
    assert (a.hips_ratio, a.shoulders_ratio, a.torso_ratio) == (0.1526, 0.1753, 0.2924)
    assert (c.select.scope, c.select.min_spacing, c.select.interval) == (50, 0.2, 0.5)
    assert c.optimize.solver == "lm"
    assert c.refine.process_noise == 0.05 and c.refine.keep_scale


def test_toml_file_and_set_overrides(tmp_path):
    f = tmp_path / "engine.toml"
    f.write_text('[select]\nscope = 80\nmin_spacing = 0.3\n\n[optimize]\nrobust = "cauchy"\n'
                 '[sync]\ninterpolate = false\n')
    c = EngineConfig.load(f)
    assert c.select.scope == 80 and c.select.min_spacing == 0.3
    assert c.optimize.robust == "cauchy" and c.sync.interpolate is False
    assert c.preprocess == EngineConfig().preprocess  # untouched sections keep their defaults
    # --set wins over the file; values are TOML (numbers, booleans, strings) or bare strings
    c = EngineConfig.load(f, ["select.scope=12", "sync.interpolate=true", "optimize.robust=huber",
                              "refine.measurement='marginal'"])
    assert c.select.scope == 12 and c.select.min_spacing == 0.3 and c.sync.interpolate is True
    assert c.optimize.robust == "huber" and c.refine.measurement == "marginal"
    assert EngineConfig.load(None, ["associate.max_distance=0.8"]).associate.max_distance == 0.8
    assert EngineConfig.load(None) == EngineConfig()
    # TOML has no null: "none" turns an optional parameter off
    c = EngineConfig.load(None, ["preprocess.confidence_reference=none", "preprocess.pixel_reference=null"])
    assert c.preprocess.confidence_reference is None and c.preprocess.pixel_reference is None


def test_unknown_keys_and_bad_values_are_errors_that_name_them(tmp_path):
    f = tmp_path / "engine.toml"
    f.write_text("[optimize]\nmax_iteration = 10\n")  # typo
    with pytest.raises(ConfigError, match=r"optimize\.max_iteration") as e:
        EngineConfig.load(f)
    assert str(f) in str(e.value)
    f.write_text("[optimise]\nmax_iterations = 10\n")  # unknown section
    with pytest.raises(ConfigError, match="optimise"):
        EngineConfig.load(f)
    with pytest.raises(ConfigError, match=r"select\.bogus"):
        EngineConfig.load(None, ["select.bogus=1"])
    with pytest.raises(ConfigError, match=r"select\.scope"):
        EngineConfig.load(None, ["select.scope=0"])  # must be >= 1
    with pytest.raises(ConfigError, match=r"optimize\.solver"):
        EngineConfig.load(None, ["optimize.solver=newton"])
    with pytest.raises(ConfigError, match="section.key=value"):
        EngineConfig.load(None, ["scope=3"])
    with pytest.raises(ConfigError, match="section.key=value"):
        EngineConfig.load(None, ["select.scope"])
    with pytest.raises(ConfigError, match="does not exist"):
        EngineConfig.load(tmp_path / "missing.toml")
    f.write_text("[select\nscope = 3\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        EngineConfig.load(f)


def test_merged_applies_nested_overrides_with_validation():
    base = EngineConfig.load(None, ["select.scope=20"])
    m = base.merged({"select": {"min_spacing": 0.5}, "refine": {"final_batch": False}})
    assert m.select.scope == 20 and m.select.min_spacing == 0.5 and m.refine.final_batch is False
    assert base.select.min_spacing == 0.2  # the original is unchanged
    with pytest.raises(ConfigError, match=r"refine\.nope"):
        base.merged({"refine": {"nope": 1}})
    with pytest.raises(ConfigError, match=r"select\.scope"):
        base.merged({"select": {"scope": -1}})


def test_config_is_frozen():
    c = EngineConfig()
    with pytest.raises(ValidationError):
        c.select.scope = 3  # type: ignore[misc]


def test_apply_override_builds_nested_dicts():
    d: dict = {}
    apply_override(d, "select.scope=7")
    apply_override(d, "select.newer_bias=1.5")
    apply_override(d, "optimize.robust=none")
    assert d == {"select": {"scope": 7, "newer_bias": 1.5}, "optimize": {"robust": "none"}}


def test_px_parameters_follow_the_image_size_once():
    from backend.config import PIXEL_FIELDS

    c = EngineConfig()
    # the lab: 16 VGA cameras and 4 of 848x480, its median is the reference: nothing changes
    lab = c.for_images([(640, 480)] * 16 + [(848, 480)] * 4)
    assert lab.preprocess.pixel_reference is None
    assert lab.model_dump(exclude={"preprocess": {"pixel_reference"}}) == c.model_dump(
        exclude={"preprocess": {"pixel_reference"}})
    hd = c.for_images([(1920, 1080)] * 3 + [(640, 480)])
    s = (1920 * 1080 / (640 * 480)) ** 0.5
    for section, names in PIXEL_FIELDS.items():
        for name in names:
            before, after = getattr(getattr(c, section), name), getattr(getattr(hd, section), name)
            assert after == pytest.approx(before * s), (section, name)
    assert hd.for_images([(320, 240)]) is hd  # already in the cameras' pixels: not scaled twice
    assert c.merged({"preprocess": {"pixel_reference": None}}).for_images([(1920, 1080)]).associate.gate_pixels == 25.0
    with pytest.raises(ConfigError, match="pixel_reference"):
        EngineConfig.from_dict({"preprocess": {"pixel_reference": [0, 480]}})


def test_every_px_parameter_is_scaled():
    """A parameter in pixels that ``for_images`` does not know would stay tuned to VGA."""
    from backend.config import PIXEL_FIELDS

    found = set()
    for section, field in EngineConfig.model_fields.items():
        for name, f in field.annotation.model_fields.items():
            text = (f.description or "").split(":")[0].split(",")[0]
            if name != "pixel_reference" and ("px" in name or "pixel" in name or text.strip() in ("px", "... up to this (px)")):
                found.add((section, name))
    assert found == {(s, n) for s, names in PIXEL_FIELDS.items() for n in names}


def test_the_monitor_watches_live_sessions_by_default_and_nothing_else():
    cfg = EngineConfig()
    assert cfg.monitor.enabled == "live" and cfg.live().monitor.enabled is True
    off = cfg.merged({"monitor": {"enabled": False}})
    assert off.live().monitor.enabled is False and off.live() is off
    assert EngineConfig.load(None, ["monitor.enabled=true"]).monitor.enabled is True
    assert EngineConfig.load(None, ['monitor.enabled="live"']).monitor.enabled == "live"
    with pytest.raises(ConfigError, match="monitor.enabled"):
        EngineConfig.load(None, ['monitor.enabled="sometimes"'])
