"""The pipeline's stages, one module each; the only code that reads or writes a Workspace.

Each stage module has a settings dataclass (`Conf`, defaults in code), named settings
(`CONFS`, e.g. pose's "paper" and "robust") and `run(workspace, conf) -> list[Path]`, the written
files; jobs that do part of a stage (one image, one camera, one frame group) are further
functions beside `run`. The algorithms they call (calib/, markers/, pose/, evaluate) take arrays,
tables and dataclasses, never paths.

    markers     detect, refine, identify          -> markers/<image>.csv, observations[/<stage>].csv
    intrinsics  calibrate each camera             -> intrinsics/<camera>.json, tables/intrinsics.csv
    extrinsics  calibrate the rig                 -> rig.json, rig_config.json, tables/extrinsics_*.csv
    pose        solve every flight frame          -> poses[_<label>].csv (+ .observations.csv)
    evaluate    errors and statistics             -> evaluation*.csv, tables/*.csv
    report      render the written results        -> report.html

Settings come from the named conf, then from `KEY=VALUE` overrides (`dmais <stage> --set`, the
workflow config's section of the stage): `configure`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping

from ..errors import DmaisError

_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def configure(confs: Mapping[str, object], name: str, overrides: Iterable[str] = (), stage: str = "") -> object:
    """The settings `confs[name]` with each override "key=value" applied (typed like the default).

    Raises DmaisError naming the stage and the unknown conf, the unknown key (with the known
    ones) or the value that does not parse.
    """
    if name not in confs:
        raise DmaisError(f"{stage}: unknown conf {name!r}; named confs: {', '.join(confs)}")
    conf = confs[name]
    fields = {f.name: getattr(conf, f.name) for f in dataclasses.fields(conf)}
    changes = {}
    for item in overrides:
        key, sep, text = str(item).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in fields:
            raise DmaisError(f"{stage}: setting {item!r} is not KEY=VALUE with KEY one of {', '.join(fields)}")
        changes[key] = _parsed(text.strip(), fields[key], f"{stage}: setting {key}")
    return dataclasses.replace(conf, **changes)


def _parsed(text: str, default, what: str):
    """`text` as a value of `default`'s type (bool, int, float, str, or a tuple of str)."""
    try:
        if isinstance(default, bool):
            if text.lower() not in _TRUE + _FALSE:
                raise ValueError
            return text.lower() in _TRUE
        if isinstance(default, tuple):
            return tuple(part.strip() for part in text.split(",") if part.strip())
        value = type(default)(text)
    except ValueError:
        raise DmaisError(f"{what}: {text!r} is not a {type(default).__name__}") from None
    if isinstance(value, float) and not value == value:
        raise DmaisError(f"{what}: {text!r} is not a number")
    return value


def settings_line(conf) -> str:
    """The conf as one log line: key=value, ..."""
    return ", ".join(f"{f.name}={getattr(conf, f.name)}" for f in dataclasses.fields(conf))
