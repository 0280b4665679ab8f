"""User-facing errors: the CLI prints these as one line, without a traceback."""


class TwohrError(Exception):
    """An error caused by the user's input or environment, with a message that says how to fix it."""


class DatasetError(TwohrError):
    """A sequence folder, file or frame that cannot be read."""


class ModelError(TwohrError):
    """A model that is unknown, missing or fails its checksum."""


class ConfigError(TwohrError):
    """A configuration value that does not validate."""


def validation_problems(exc, empty_location: str = "", skip: tuple[str, ...] = ()) -> str:
    """A pydantic ``ValidationError`` as one line: ``loc.path: message; ...``.

    ``skip`` drops location parts (e.g. FastAPI's ``body``); ``empty_location`` names an error at the root."""
    problems = []
    for e in exc.errors():
        where = ".".join(str(p) for p in e["loc"] if p not in skip) or empty_location
        message = e["msg"].removeprefix("Value error, ")  # a validator's own message says it all
        problems.append(f"{where}: {message}" if where else message)
    return "; ".join(problems)
