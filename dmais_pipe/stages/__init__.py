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
workflow config's section of the stage): `configure`. Each setting is declared with `setting`, which
carries its description: `dmais <stage> --help` lists every setting with its default
(`settings_help`), and the workflow schema repeats the same descriptions and defaults (a test
holds them equal).
"""

from __future__ import annotations

import dataclasses
import textwrap
from collections.abc import Iterable, Mapping

from ..errors import DmaisError

_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def setting(default, help: str, minimum: float | None = None, above: float | None = None):
    """A Conf field with its description (shown by `dmais <stage> --help` and in the workflow schema)
    and the range an override must keep: >= minimum, > above."""
    return dataclasses.field(default=default, metadata={"help": help, "minimum": minimum, "above": above})


def setting_help(field: dataclasses.Field) -> str:
    return field.metadata.get("help", "")


def settings_help(confs: Mapping[str, object]) -> str:
    """The stage's settings and named confs as `--help` text: every setting with the default conf's
    value and its description, then each named conf with what it changes."""
    default = next(iter(confs.values()))
    fields = dataclasses.fields(default)
    width = max(len(f.name) for f in fields) + 2
    lines = ["settings (--set KEY=VALUE; default in brackets):"]
    for field in fields:
        text = f"{setting_help(field)} [{_text(getattr(default, field.name))}]".strip()
        lines.append(textwrap.fill(text, 100, initial_indent=f"  {field.name:<{width}}",
                                   subsequent_indent=" " * (width + 2)))
    lines.append("named confs (--conf NAME):")
    for name, conf in confs.items():
        changed = [f"{f.name}={_text(getattr(conf, f.name))}" for f in fields
                   if getattr(conf, f.name) != getattr(default, f.name)]
        lines.append(f"  {name:<{width}}{', '.join(changed) if changed else 'the defaults'}")
    return "\n".join(lines)


def _text(value) -> str:
    """A setting's value as it is written after --set KEY=."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        return ",".join(str(v) for v in value)
    return str(value) if value != "" else "''"


def configure(confs: Mapping[str, object], name: str, overrides: Iterable[str] = (), stage: str = "") -> object:
    """The settings `confs[name]` with each override "key=value" applied (typed like the default).

    Raises DmaisError naming the stage and the unknown conf, the unknown key (with the known
    ones) or the value that does not parse.
    """
    if name not in confs:
        raise DmaisError(f"{stage}: unknown conf {name!r}; named confs: {', '.join(confs)}")
    conf = confs[name]
    declared = {f.name: f for f in dataclasses.fields(conf)}
    fields = {name: getattr(conf, name) for name in declared}
    changes = {}
    for item in overrides:
        key, sep, text = str(item).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in fields:
            raise DmaisError(f"{stage}: setting {item!r} is not KEY=VALUE with KEY one of {', '.join(fields)}")
        changes[key] = _parsed(text.strip(), fields[key], f"{stage}: setting {key}")
        _check_range(changes[key], declared[key].metadata, f"{stage}: setting {key}")
    return dataclasses.replace(conf, **changes)


def three_numbers(items: tuple, what: str) -> tuple[float, float, float]:
    """A tuple setting of three finite numbers x, y, z (e.g. a lever arm in m) as floats; DmaisError
    naming `what` ("<stage>: setting <key>") otherwise."""
    try:
        values = tuple(float(v) for v in items)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(v - v == 0 for v in values):  # finite
        raise DmaisError(f"{what}: {','.join(map(str, items))!r} is not three numbers x,y,z (m)")
    return values


def _check_range(value, metadata, what: str) -> None:
    minimum, above = metadata.get("minimum"), metadata.get("above")
    if minimum is not None and value < minimum:
        raise DmaisError(f"{what}: {value} is below its minimum {minimum}")
    if above is not None and value <= above:
        raise DmaisError(f"{what}: {value} must be above {above}")


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
