"""twohr common library: the contracts every service shares.

Modules:

* data and maths: ``config`` (typed pipeline configuration), ``dataset`` (TUM-layout RGB-D sequences),
  ``features`` (keypoints, detections, matches), ``geometry`` (SE(3), quaternions, Umeyama),
  ``trajectory`` (TUM trajectory I/O), ``evaluation`` (ATE/RPE as in the TUM tools and evo),
  ``synthetic`` (exact synthetic sequences),
  ``models`` (verified model registry, ``models.yaml``), ``plots``;
* the bus: ``keys`` (key expressions), ``messages`` (typed bus messages), ``bus`` (sessions, router,
  health query), ``identity`` (a fleet's key folders and robot bundles), ``service`` (the services' shell),
  ``workers`` (background worker, prefetcher);
* recordings and views: ``mcapfile`` (crash-safe MCAP files), ``foxglove_convert`` (twohr data as
  Foxglove messages), ``foxglove_live`` (the Foxglove WebSocket live view);
* odds and ends: ``errors`` (user-facing errors), ``paths`` (the dev sequence, paths under data roots).
"""

__version__ = "0.1.0"
