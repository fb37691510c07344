"""Markdown tables of result rows (``summary.md``, the evaluation reports)."""


def markdown_table(rows: list, columns: list) -> str:
    """A markdown table of ``rows`` (dicts) with ``columns`` ``[(key, title), ...]``; floats with 3 digits."""

    def cell(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(t for _, t in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(r.get(k)) for k, _ in columns) + " |" for r in rows]
    return "\n".join(lines)
