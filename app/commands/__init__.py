"""One module per ``twohr`` command, each with a ``register(subparsers)`` function (see :mod:`twohr_app.cli`)."""
