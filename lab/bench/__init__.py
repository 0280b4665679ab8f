"""``twohr bench``: the bench as a family of studies, one module each, over library steps without a command line.

Each study module (:data:`twohr_lab.bench.cli.STUDIES`: throughput, ablations, networks, view, view_tls, bus, live,
soak, fleet, share) holds one parser builder (``add_arguments``) and one short pipeline (``run``) that returns its
part of ``bench.json``; :mod:`~twohr_lab.bench.common` holds what they share (options, the output folder, the
report files). The steps they call live in :mod:`twohr_lab.bench.steps`: timed runs of the pipeline, the ablation
rows, live camera sessions on a stack, the fleet's keyframe-job replay, two robots sharing a map.

``twohr bench <study> [options]`` runs one study; every spelling of the flags of before (``twohr bench --live
--robots 2``, ``--fleet N``, ``--bus --rate 1``, ``--frames 560 --runs 3`` …) picks the same study as it did.
"""
