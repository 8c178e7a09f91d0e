"""The parameter reference ``docs/parameters.md``, generated from :mod:`fleetmap.shared.config`, the
two presets and :data:`~fleetmap.shared.config_files.RETIRED` (tests/test_docs.py checks it is up
to date)::

    python -m fleetmap.parameters_doc docs/parameters.md
"""

from __future__ import annotations

import sys
from pathlib import Path

from fleetmap.config_args import PRESETS, field_docs, preset
from fleetmap.shared.config import SECTIONS, FleetmapConfig, parameters
from fleetmap.shared.config_files import RETIRED

COMMAND = "python -m fleetmap.parameters_doc docs/parameters.md"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render() -> str:
    """The reference, as Markdown."""
    defaults = FleetmapConfig().flat()
    modes = {mode: preset(mode).flat() for mode in PRESETS}  # type: ignore[arg-type]
    lines = [
        "# Parameters",
        "",
        f"Generated from `shared/config.py` by `{COMMAND}`: do not edit by hand.",
        "",
        f"fleetmap has {len(parameters())} parameters: the paper's (`paper`, Amigoni, Gasparini & Gini 2006, with",
        "its defaults) and those fleetmap adds (`fleetmap`), each set in a TOML table of a config file",
        "(`--config FILE`) or by its option (`--name-with-dashes VALUE`). `basic` ones are those a user sets for",
        "their robots (`fleetmap/examples/basic.toml`); `fleetmap map --help-all` lists them all. Why each is a",
        "parameter, and where the values that are not went: `docs/decisions/005-parameters-beyond-the-paper.md`.",
        "",
        "## Presets",
        "",
        "A live fleet (`fleetmap run`, `agent`, `merger`) starts from `fleetmap/examples/live.toml`, an offline",
        "run (`fleetmap map`, `merge`) from `offline.toml`; a `--config` file is read on top, options on top of both.",
        "",
        "| parameter | default | live | offline |",
        "|---|---|---|---|",
    ]
    for key, value in defaults.items():
        if any(modes[m][key] != value for m in modes):
            lines.append(f"| `{key}` | {value!r} | {modes['live'][key]!r} | {modes['offline'][key]!r} |")
    for path in SECTIONS:
        docs = field_docs(SECTIONS[path])
        lines += ["", f"## [{path}]", "", "| parameter | default | tag | what it does |", "|---|---|---|---|"]
        for where, f in parameters():
            if where != path:
                continue
            tag = f.metadata["origin"] + (", basic" if f.metadata["basic"] else "")
            value = defaults[f"{path}.{f.name}"]
            lines.append(f"| `{f.name}` | {value!r} | {tag} | {_cell(docs.get(f.name, ''))} |")
    lines += [
        "",
        "## Retired parameters",
        "",
        "Module constants now, each with a line saying why its value. A config file or a recording's config that",
        "names one still loads: at its fixed value said at INFO, at another value with a WARNING (the run uses the",
        "fixed value).",
        "",
        "| table | parameter | fixed at | constant |",
        "|---|---|---|---|",
    ]
    for table, entries in RETIRED.items():
        for name, retired in entries.items():
            where = f"`fleetmap.{retired.constant}`" if retired.constant else "(removed)"
            fixed = "-" if retired.value is None else repr(retired.value)
            lines.append(f"| [{table}] | `{name}` | {fixed} | {where} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print(f"usage: {COMMAND}", file=sys.stderr)
        return 2
    Path(args[0]).write_text(render(), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
