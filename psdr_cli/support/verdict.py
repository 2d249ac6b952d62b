"""One verdict on a gradient's agreement with finite differences, shared by ``psdr grad --fd`` and
the test suite (``tests/test_gradients.py``), so the CLI never calls "agrees" what a test rejects.

The statistics come from :func:`psdr_cli.rendering.reference.agreement`: z = (estimate − FD)/√(se² + se_FD²)
on the image sum and on B×B tiles (where no FD batch changed at all on a tile, se_FD is the
change one flipped sample would make: :func:`psdr_cli.rendering.reference.fd_resolution`). A gradient
agrees when every criterion holds:

- image sum: |z| < 3;
- tiles within 3 SE: ≥ 90 %;
- mean z² over tiles < 2.5 (≈ 1 when the two differ by noise only);
- max |z| over signal tiles (FD > 3 of its SE) < 5 (one 5σ tile in 64 happens by chance with
  probability ≈ 4·10⁻⁵; a biased pixel block shows here even when the sum agrees);
- correlation of the tile sums > 0.85;
- at least ``min_signal`` signal tiles (otherwise the comparison has too little power).
"""
from __future__ import annotations

#: (name, statistic, test, printed threshold)
CRITERIA = (
    ("sum |z|", lambda a: abs(a["sum"]["z"]), lambda x: x < 3, "< 3"),
    ("tiles within 3 SE", lambda a: a["blocks"]["within_3se"], lambda x: x >= 0.9, "≥ 90%"),
    ("mean z²", lambda a: a["blocks"]["mean_z2"], lambda x: x < 2.5, "< 2.5"),
    ("max |z| (signal tiles)", lambda a: a["blocks"]["max_abs_z_signal"], lambda x: x < 5, "< 5"),
    ("correlation", lambda a: a["blocks"]["correlation"], lambda x: x > 0.85, "> 0.85"),
)


def checks(stats: dict, min_signal: int = 10) -> list:
    """[(criterion, value, passed, threshold)] for one view's agreement statistics."""
    out = [(name, value(stats), bool(test(value(stats))), thr) for name, value, test, thr in CRITERIA]
    signal = stats["blocks"]["signal"]
    out.append(("signal tiles", signal, signal >= min_signal, f"≥ {min_signal}"))
    return out


def agrees(stats: dict, min_signal: int = 10) -> bool:
    """Whether every criterion of :func:`checks` holds."""
    return all(ok for _, _, ok, _ in checks(stats, min_signal))


def describe(stats: dict, min_signal: int = 10) -> str:
    """One line per criterion, e.g. ``sum |z| = 0.41 (< 3) ok``."""
    lines = []
    for name, value, ok, thr in checks(stats, min_signal):
        shown = f"{100 * value:.0f}%" if name == "tiles within 3 SE" else (f"{value:.3g}" if isinstance(value, float) else str(value))
        lines.append(f"  {name} = {shown} ({thr}) {'ok' if ok else 'FAILS'}")
    return "\n".join(lines)
