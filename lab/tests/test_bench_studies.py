"""``twohr bench`` as a family of studies: one module and one parser builder per study under ``lab/bench/``, and
every spelling of before still picking the same study with the same options (parsed here, not run: the runs
themselves are in the bench's other tests)."""

from __future__ import annotations

from pathlib import Path

import pytest

from twohr import keys
from twohr_app.cli import build_parser
from twohr_lab.bench import cli
from twohr_lab.bench.fleet import server_stages

BENCH = Path(cli.__file__).parent
#: the modules of lab/bench/ that are not studies
NOT_STUDIES = {"__init__", "cli", "common"}


def parse(*argv: str):
    return build_parser().parse_args(["bench", *argv])


def test_the_bench_holds_one_module_per_study_and_at_least_eight():
    modules = {path.stem for path in BENCH.glob("*.py")} - NOT_STUDIES
    assert len(modules) >= 8
    assert modules == set(cli.BY_NAME) == {study.__name__.rsplit(".", 1)[1] for study in cli.STUDIES}
    for name, study in cli.BY_NAME.items():
        assert study.NAME == name and Path(study.__file__).parent == BENCH
        assert callable(study.add_arguments) and callable(study.run) and callable(study.picked) and study.HELP
    assert cli.STUDIES[-1] is cli.BY_NAME["throughput"]  # what runs without a study's flag


#: today's spellings -> the study each picks and what it reads from the command line
SPELLINGS = [
    ([], "throughput", {"frames": None, "runs": 3}),
    (["--frames", "560", "--runs", "3", "--set", "detector.precision=f32"], "throughput",
     {"frames": 560, "runs": 3, "set": ["detector.precision=f32"]}),
    (["--ablations", "--out", "results/ablations"], "ablations", {"out": "results/ablations"}),
    (["--networks", "--runs", "3"], "networks", {"runs": 3}),
    (["--view"], "view", {}),
    (["--view-tls", "--frames", "200", "--runs", "2"], "view_tls", {"frames": 200, "runs": 2}),
    (["--bus", "--frames", "560", "--runs", "2", "--rate", "1"], "bus", {"rate": 1.0, "robots": None}),
    (["--bus", "--robots", "2"], "bus", {"robots": 2, "rate": 1.0, "gateway": None}),
    (["--bus", "--gateway", "http://127.0.0.1:8080", "--router", "tcp/10.0.0.2:7447", "--api-token", "t" * 16],
     "bus", {"gateway": "http://127.0.0.1:8080", "router": "tcp/10.0.0.2:7447", "api_token": "t" * 16}),
    (["--fleet", "2", "--frames", "120"], "fleet", {"fleet": 2, "frames": 120, "server_stages": None}),
    (["--fleet", "6", "--server-stages", "detector"], "fleet", {"fleet": 6, "server_stages": "detector"}),
    (["--fleet", "4", "--replicas", "detector=2", "--replicas", "yolo=2"], "fleet",
     {"replicas": ["detector=2", "yolo=2"]}),
    (["--live"], "live", {"busy": "0,1,2", "link": "tcp", "edge": False, "robots": None, "camera_runs": 1}),
    (["--live", "--robots", "2", "--runs", "3", "--frames", "300", "--edge", "--busy", "0"], "live",
     {"robots": 2, "runs": 3, "frames": 300, "edge": True, "busy": "0"}),
    (["--live", "--link", "both", "--frames", "560", "--camera-runs", "6"], "live",
     {"link": "both", "camera_runs": 6}),
    (["--live", "--soak", "5"], "soak", {"soak": 5.0, "soak_busy": 0}),
    (["--soak", "5", "--soak-busy", "1"], "soak", {"soak": 5.0, "soak_busy": 1}),
    (["--share"], "share", {"runs": 3}),
    (["--share", "--runs", "4"], "share", {"runs": 4}),
    # several flags: the first of fleet, share, soak, live, bus, view-tls, view, networks, ablations, as before
    (["--ablations", "--networks"], "networks", {}),
    (["--view", "--view-tls"], "view_tls", {}),
    (["--bus", "--live"], "live", {}),
    (["--share", "--fleet", "2"], "fleet", {}),
]


@pytest.mark.parametrize(("argv", "study", "values"), SPELLINGS, ids=[" ".join(s[0]) or "(none)" for s in SPELLINGS])
def test_every_spelling_of_before_picks_its_study(argv, study, values):
    args = parse(*argv)
    assert cli.chosen_study(args).NAME == study
    assert args.study is None and args.func is cli.main
    assert {key: getattr(args, key) for key in values} == values


@pytest.mark.parametrize(("named", "flags"), [
    (["live", "--robots", "2", "--edge", "--frames", "300"], ["--live", "--robots", "2", "--edge", "--frames", "300"]),
    (["fleet", "--robots", "6", "--server-stages", "detector"], ["--fleet", "6", "--server-stages", "detector"]),
    (["soak", "--minutes", "5", "--busy", "1"], ["--soak", "5", "--soak-busy", "1"]),
    (["bus", "--rate", "0", "--robots", "2"], ["--bus", "--rate", "0", "--robots", "2"]),
    (["throughput", "--frames", "30", "--runs", "1"], ["--frames", "30", "--runs", "1"]),
])
def test_a_study_by_name_reads_what_its_flags_read(named, flags):
    """``twohr bench <study>``: the options given before the study's name count, the ones not given keep the
    defaults of ``twohr bench``."""
    by_name, by_flags = vars(parse("--sequence", "S", "--quiet", *named)), vars(parse("--sequence", "S", "--quiet",
                                                                                     *flags))
    assert cli.BY_NAME[by_name.pop("study")] is cli.chosen_study(parse(*flags))
    by_flags.pop("study")
    differ = {key for key in by_name if by_name[key] != by_flags[key]}
    assert differ <= {"live", "bus"}, differ  # the study's own flag, which naming it replaces


def test_a_study_by_name_takes_only_its_own_options():
    with pytest.raises(SystemExit):
        parse("view", "--robots", "2")
    with pytest.raises(SystemExit):
        parse("fleet")  # how many robots is not optional


def test_the_fleet_bench_serves_all_three_networks_unless_told():
    assert server_stages(parse("--fleet", "4")) == tuple(keys.NETWORK_SERVICES) == ("detector", "yolo", "matcher")
    assert server_stages(parse("--fleet", "4", "--server-stages", "detector")) == ("detector",)
