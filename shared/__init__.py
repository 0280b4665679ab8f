"""twohr common library: the contracts every service shares (``docs/architecture.md`` lists each module).

Modules:

* data and maths: ``config`` (typed pipeline configuration), ``dataset`` (TUM-layout RGB-D sequences),
  ``features`` (keypoints, detections, matches), ``geometry`` (SE(3), quaternions, Umeyama), ``pose`` (pose
  estimation), ``places`` (place recognition and the verification of a candidate place), ``quantise`` (INT8
  keyframe networks), ``trajectory`` (TUM trajectory I/O), ``evaluation`` (ATE/RPE as in the TUM tools and evo),
  ``synthetic`` (exact synthetic sequences), ``models`` (verified model registry, ``models.yaml``), ``machine``
  (where a figure was measured);
* maps: ``mapfile`` (the map file format), ``mapstore`` (the folder of maps: versions, owners, grants),
  ``mapmodes`` (what a session does with a map, and the rules of each mode), ``mapclient`` (the map room over the
  bus), ``keyframe_sender`` (what a tracker sends of its keyframes to a shared map), ``audit`` (the audit trail);
* the bus: ``keys`` (key expressions), ``ids`` (robot ids and reserved names), ``messages`` (typed bus messages),
  ``bus`` (sessions, router, health query), ``identity`` (a fleet's key folders and robot bundles), ``service``
  (the services' shell), ``replicas`` (a network service's replicas), ``rates`` (admitted rates, the replay pacer),
  ``workers`` (background worker, prefetcher);
* recordings and views: ``mcapfile`` (crash-safe MCAP files), ``foxglove_convert`` (twohr data as
  Foxglove messages), ``foxglove_live`` (the Foxglove WebSocket live view);
* odds and ends: ``errors`` (user-facing errors), ``paths`` (the dev sequence, paths under data roots), ``files``
  (atomic file writes).
"""

__version__ = "0.1.0"
