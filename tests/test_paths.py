import pytest

from twohr.errors import TwohrError
from twohr.paths import resolve_under_roots


def test_paths_must_stay_under_roots(tmp_path):
    root = tmp_path / "data"
    (root / "seq").mkdir(parents=True)
    (tmp_path / "secret").mkdir()
    (root / "link").symlink_to(tmp_path / "secret")
    assert resolve_under_roots("seq", [root]) == (root / "seq").resolve()
    assert resolve_under_roots(str(root / "seq"), [root]) == (root / "seq").resolve()
    for bad, match in [("../secret", r"'\.\.'"), (str(tmp_path / "secret"), "not under"), ("link", "not under"),
                       ("nope", "not under|not found"), ("", "empty")]:
        with pytest.raises(TwohrError, match=match):
            resolve_under_roots(bad, [root])
