import pytest

from twohr.config import PipelineConfig, load_config
from twohr.errors import ConfigError


def test_defaults_are_valid():
    cfg = PipelineConfig()
    assert cfg.detector.reliability_clusters == 3 and cfg.detector.repeatability_clusters == 2
    assert cfg.yolo.remove_levels == ["high"]


def test_file_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("detector:\n  max_keypoints: 800\nyolo:\n  enabled: false\n")
    overrides = ["detector.max_keypoints=900", "tracker.min_inliers=30", "yolo.remove_levels=[high, medium]"]
    cfg = load_config(path, overrides)
    assert cfg.detector.max_keypoints == 900
    assert cfg.yolo.enabled is False
    assert cfg.tracker.min_inliers == 30
    assert cfg.yolo.remove_levels == ["high", "medium"]


@pytest.mark.parametrize("override,match", [
    ("detector.nonsense=1", "detector.nonsense"),
    ("detector.max_keypoints=-5", "detector.max_keypoints"),
    ("matcher.method=magic", "matcher.method"),
    ("no_equals_sign", "key=value"),
])
def test_bad_overrides_are_clear(override, match):
    with pytest.raises(ConfigError, match=match):
        load_config(None, [override])


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "absent.yaml")


def test_presets_sit_between_the_file_and_the_overrides(tmp_path):
    from twohr.config import PRESETS

    path = tmp_path / "c.yaml"
    path.write_text("detector:\n  features: r2d2\n  max_keypoints: 800\n")
    cfg = load_config(path, ["matcher.method=siamese"], preset="orb")
    assert cfg.detector.features == "orb" and cfg.yolo.enabled is False  # the preset over the file
    assert cfg.detector.max_keypoints == 800  # what the preset does not name stays the file's
    assert cfg.matcher.method == "siamese"  # --set over the preset
    full = load_config(preset="full")
    assert (full.detector.features, full.yolo.enabled, full.matcher.method) == ("2hr", True, "siamese")
    assert load_config(preset="full-no-final-ba").tracker.final_ba_iterations == 0
    assert len({p.label for p in PRESETS.values()}) == len(PRESETS)  # one table row each


def test_an_unknown_preset_names_the_known_ones():
    with pytest.raises(ConfigError, match="unknown preset 'fast'.*orb.*full"):
        load_config(preset="fast")
