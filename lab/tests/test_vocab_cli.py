"""``twohr vocab``: a vocabulary trained on some frames, installed, listed and evaluated on others."""

import json
import os
import subprocess
import sys


def _twohr(*args, env):
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True,
                          timeout=300, env=env)


def test_train_list_and_evaluate_a_vocabulary(dev_sequence, tmp_path):
    env = dict(os.environ, TWOHR_VOCABULARIES=str(tmp_path / "installed"))
    common = ["--sequence", str(dev_sequence), "--cache", str(tmp_path / "cache"), "--step", "4"]
    done = _twohr("vocab", "train", *common, "--start", "0", "--frames", "24", "--words", "32", "--name", "tiny",
                  "--out", str(tmp_path / "out"), env=env)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "out" / "tiny.npz").is_file() and (tmp_path / "installed" / "tiny.npz").is_file()
    card = (tmp_path / "out" / "tiny.md").read_text()
    assert "words: 32" in card and "frames 0-20, step 4" in card and "non-commercial" in card

    listed = _twohr("vocab", "list", env=env)
    assert listed.returncode == 0 and "tiny" in listed.stdout and "0-20" in listed.stdout, listed.stdout

    evaluated = _twohr("vocab", "eval", *common, "--start", "24", "--frames", "40", "--min-gap", "12",
                       "--name", "tiny", "--out", str(tmp_path / "eval"), env=env)
    assert evaluated.returncode == 0, evaluated.stderr
    report = json.loads((tmp_path / "eval" / "place_recognition.json").read_text())
    assert report["trained_on"] == "0-20" and report["evaluated_on"] == "24-60" and report["queries"] == 10
    for row in report["queries_detail"]:
        assert abs(row["best"] - row["query"]) >= 12 and -1e-6 <= row["score"] <= 1 + 1e-6

    missing = _twohr("vocab", "eval", *common, "--name", "nothing", env=env)
    assert missing.returncode == 2 and "twohr vocab train" in missing.stderr, missing.stderr
