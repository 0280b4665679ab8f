"""``twohr_app``: the composition root. It assembles the service rooms (``twohr_services``) and the common
library (``twohr``) into the program people run; no service imports it.

- :mod:`twohr_app.cli`: the ``twohr`` parser; one module per command in :mod:`twohr_app.commands`
  (``run`` and ``demo``, ``up``, ``camera``, ``maps``, ``health``, ``router``, ``eval``, ``synth``, ``models``).
- :mod:`twohr_app.pipeline`: the cores composed in one process (``twohr run``, the lab's benches).
- :mod:`twohr_app.supervisor`: the stack as local processes (router, services, gateway) under supervision.
- :mod:`twohr_app.access`: what each role may do on the bus, the routers' access-control lists.
- :mod:`twohr_app.fleet`: every credential: passwords, tokens, users lists, a fleet's certificates and keys folder.
- :mod:`twohr_app.report`, :mod:`twohr_app.live_view`: a run's plots and report page; its live Foxglove view.
"""
