"""The benchmarks' result table: metric, value, target, met?; rows starting with '## ' are section headers."""


def print_table(rows: list[tuple[str, str, str, str]], notes: list[str]) -> None:
    header = ("metric", "value", "target", "met?")
    body = [r for r in rows if not r[0].startswith("## ")]
    widths = [max(len(r[i]) for r in [*body, header]) for i in range(4)]
    inner = sum(widths) + 3 * (len(widths) - 1)
    line = "+-" + "-+-".join("-" * w for w in widths) + "-+"

    def show(r: tuple[str, ...]) -> None:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |")

    print(line)
    show(header)
    for r in rows:
        if r[0].startswith("## "):
            print(line)
            print("| " + r[0][3:][:inner].ljust(inner) + " |")
            print(line)
        else:
            show(r)
    print(line)
    for n in notes:
        print(n)


def met(ok: bool | None) -> str:
    """'yes' or 'NO' for a target, '' where there is none."""
    return "" if ok is None else ("yes" if ok else "NO")


def print_grid(header: list[str], rows: list[list[str] | str]) -> None:
    """A table of any columns: `header`, then rows of cells; a row given as text is a section line across it."""
    widths = [max(len(r[i]) for r in [header, *rows] if isinstance(r, list)) for i in range(len(header))]
    line = "+-" + "-+-".join("-" * w for w in widths) + "-+"

    def show(r: list[str]) -> None:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |")

    print(line)
    show(header)
    print(line)
    for r in rows:
        if isinstance(r, str):
            print("| " + r.ljust(len(line) - 4) + " |")
            print(line)
        else:
            show(r)
    print(line)
