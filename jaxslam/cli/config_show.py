"""``jaxslam config show``: every key of a resolved study config, its value in TOML syntax and
its unit (``jaxslam.columns.CONFIG_UNITS``)."""
from __future__ import annotations

import math

from jaxslam.cli.common import _load_config
from jaxslam.cli.study import demo_config
from jaxslam.columns import CONFIG_UNITS, config_unit  # noqa: F401 (units table)


def toml_value(value) -> str:
    """A config value in TOML syntax (what ``--set KEY=VALUE`` reads back): 64, 0.5, true,
    "loop", inf, [0.0, 0.06, 0.0002]. Floats keep 6 significant digits."""
    import json

    import numpy as np

    if hasattr(value, "__array__") and not isinstance(value, (list, tuple)):
        array = np.asarray(value)  # NumPy or JAX array: a scalar or a flat list
        value = array.item() if array.ndim == 0 else array.ravel().tolist()
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    number = float(value)
    if math.isnan(number):
        return "nan"
    if math.isinf(number):
        return "inf" if number > 0 else "-inf"
    text = f"{number:.6g}"
    return text if any(c in text for c in ".e") else text + ".0"


def config_rows(config) -> list[tuple[str, str, str, str]]:
    """(key, value, unit, note) of every entry of a resolved study config.

    Study, [filter] and [scenario] keys come from ``study_config_to_dict``; [params] lists
    every ``Params`` field with the value the filter runs with (note "set in the config",
    "= scenario.max_range" or "default"); [sweep] lists the swept values.
    """
    from jaxslam import studies
    from jaxslam.types import default_params

    data = studies.study_config_to_dict(config)
    rows = []
    for section in ("", "filter", "scenario"):
        items = data[section].items() if section else (
            (k, v) for k, v in data.items() if not isinstance(v, dict))
        for key, value in items:
            name = f"{section}.{key}" if section else key
            rows.append((name, toml_value(value), config_unit(name), ""))
    given, swept = dict(config.params), dict(config.sweep)
    resolved = default_params(config.filter, **{"max_range": config.scenario.max_range,
                                                **given})
    for key, value in resolved._asdict().items():
        note = (f"swept: see sweep.{key}" if key in swept else
                "set in the config" if key in given else
                "= scenario.max_range" if key == "max_range" else
                "= sqrt(association_gate)" if key == "airlock_sigmas" else "default")
        rows.append((f"params.{key}", toml_value(value), config_unit(f"params.{key}"), note))
    for key, values in data["sweep"].items():
        rows.append((f"sweep.{key}", toml_value(values), config_unit(f"sweep.{key}"),
                     "swept: one condition per value"))
    return rows


def format_config_rows(rows) -> list[str]:
    """Aligned "key  value  unit  # note" lines with a header."""
    header = ("# key", "value", "unit", "")
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(3)]
    lines = []
    for key, value, unit, note in [header, *rows]:
        line = f"{key:<{widths[0]}}  {value:<{widths[1]}}  {unit:<{widths[2]}}"
        lines.append((line + (f"  # {note}" if note else "")).rstrip())
    return lines


def cmd_config_show(args) -> int:
    """Print the resolved study config: every key, its value and its unit."""
    if args.file is None:
        config = demo_config(args.set)
        source = "the demo config (`jaxslam demo`)"
    else:
        config = _load_config(args.file, args.set)
        source = str(args.file)
    overrides = f" with {len(args.set)} --set override(s)" if args.set else ""
    print(f"# study config {config.name!r}: {source}{overrides}; "
          f"{len(config.conditions)} condition(s)")
    print("# values in TOML syntax: each line works as --set KEY=VALUE")
    for line in format_config_rows(config_rows(config)):
        print(line)
    return 0
