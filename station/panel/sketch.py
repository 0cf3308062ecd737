"""A sketch of where a reference point is, for a prompt whose cell file gives no picture of it: the cell seen
from above (robot base frame, x to the right, y up), the robot base at the origin, every reference point, the
one asked about in red with its position in mm. Plain SVG, drawn here: the page loads it like a picture."""

from __future__ import annotations

from html import escape

import numpy as np

SIZE = 360  # px of the square drawing
MARGIN = 40


def point_sketch(cell, label: str) -> str:
    pts = {lb: np.asarray(p.position, float)[:2] for lb, p in cell.points.items()}
    xy = np.array([[0.0, 0.0], *pts.values()])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = float(max(hi[0] - lo[0], hi[1] - lo[1], 0.05))  # m; at least 5 cm across
    centre = (lo + hi) / 2
    scale = (SIZE - 2 * MARGIN) / span  # px per m, the same on both axes

    def px(p) -> tuple[float, float]:
        return (SIZE / 2 + (p[0] - centre[0]) * scale, SIZE / 2 - (p[1] - centre[1]) * scale)

    bx, by = px((0.0, 0.0))
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{SIZE}" height="{SIZE}" viewBox="0 0 {SIZE} {SIZE}" '
           f'data-scale-px-per-m="{scale:.6g}">',
           f'<rect width="{SIZE}" height="{SIZE}" fill="#ffffff" stroke="#9ca3af"/>',
           '<text x="8" y="18" font-size="12" fill="#374151">cell from above (x right, y up)</text>',
           f'<rect id="base" x="{bx - 9:.1f}" y="{by - 9:.1f}" width="18" height="18" fill="#6b7280"/>',
           f'<line x1="{bx:.1f}" y1="{by:.1f}" x2="{bx + 30:.1f}" y2="{by:.1f}" stroke="#2563eb" stroke-width="2"/>',
           f'<line x1="{bx:.1f}" y1="{by:.1f}" x2="{bx:.1f}" y2="{by - 30:.1f}" stroke="#16a34a" stroke-width="2"/>',
           f'<text x="{bx + 12:.1f}" y="{by + 22:.1f}" font-size="12" fill="#374151">robot base</text>']
    for lb, p in pts.items():
        if lb == label:
            continue
        x, y = px(p)
        out.append(f'<circle cx="{x:.2f}" cy="{y:.2f}" r="5" fill="#9ca3af"/>'
                   f'<text x="{x + 8:.1f}" y="{y + 4:.1f}" font-size="12" fill="#6b7280">{escape(lb)}</text>')
    x, y = px(pts[label])
    pos = np.asarray(cell.points[label].position, float) * 1e3
    out.append(f'<circle id="target" cx="{x:.2f}" cy="{y:.2f}" r="11" fill="none" stroke="#dc2626" '
               f'stroke-width="4"/><circle cx="{x:.2f}" cy="{y:.2f}" r="3" fill="#dc2626"/>'
               f'<text x="{x + 14:.1f}" y="{y - 10:.1f}" font-size="16" font-weight="bold" fill="#dc2626">'
               f'{escape(label)}</text>')
    out.append(f'<text x="8" y="{SIZE - 10}" font-size="13" fill="#111827">point {escape(label)} at x '
               f'{pos[0]:.0f} mm, y {pos[1]:.0f} mm, z {pos[2]:.0f} mm</text></svg>')
    return "".join(out)
