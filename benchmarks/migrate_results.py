"""One-off: today's RESULTS.md sections as ``benchmarks/results/<section>.json`` (issue 51).

Each section's command, date, commit and dirty flag are read from its first line, its body kept as
it is and its figures read from its tables; the config it ran with was not recorded, so its hash is
None. Checks that rendering the results gives RESULTS.md's sections back unchanged.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results import CHECKOUT, FOLDER, RESULTS, dump_result, figures, load_results, render_markdown

SECTION = re.compile(
    r"<!-- section: (?P<name>[^ ]+) -->\n## (?P<title>[^\n]*)\n\n(?P<line>[^\n]*)\n\n"
    r"(?P<body>.*?)(?=\n<!-- section: |\Z)",
    re.S,
)
LINE = re.compile(
    r"`(?P<command>.*)` on (?P<date>\d{4}-\d\d-\d\d), "
    r"commit (?P<commit>[0-9a-f]+)(?P<dirty>\+?)(?: \((?P<note>.*)\))?\.$"
)


def main() -> int:
    text = (CHECKOUT / RESULTS).read_text(encoding="utf-8")
    folder = CHECKOUT / FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    first = text.index("<!-- section: ")
    for m in SECTION.finditer(text):
        line = LINE.match(m["line"])
        if line is None:
            raise SystemExit(f"section {m['name']}: cannot read {m['line']!r}")
        result = {
            "section": m["name"],
            "title": m["title"],
            "command": line["command"],
            "date": line["date"],
            "commit": line["commit"],
            "dirty": line["dirty"] == "+",
            "config_hash": None,
            "config_varied": [],
            "figures": figures(m["body"]),
            "body": m["body"].strip(),
        }
        if line["note"]:
            result["note"] = line["note"]
        (folder / f"{m['name']}.json").write_text(dump_result(result), encoding="utf-8")
    rendered = render_markdown(load_results(folder))
    again = rendered[rendered.index("<!-- section: ") :]
    if again != text[first:]:
        (Path("/tmp") / "RESULTS.rendered.md").write_text(rendered, encoding="utf-8")
        print("rendered sections differ from RESULTS.md: see /tmp/RESULTS.rendered.md", file=sys.stderr)
        return 1
    print(f"{len(list(folder.glob('*.json')))} sections; rendered as RESULTS.md has them")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
