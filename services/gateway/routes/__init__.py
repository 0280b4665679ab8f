"""The gateway's HTTP routes, one ``APIRouter`` per resource: ``sessions``, ``maps``, ``audit`` and ``health``
(the session page's routes are in ``..page``). ``create_app`` includes them."""
