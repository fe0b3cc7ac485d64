"""report.html: one self-contained page for a road inspector: the route with the potholes
coloured by severity, a sortable table, a picture of each pothole at its best view, the
distribution of depths and areas, the observed length of road, and the frames that could not
be processed: how many, why and where in the drive (and bags that could not be read)."""

from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from ..params import PARAMETER_BY_NAME
from .drive import SEVERITIES, DriveSurvey, SurveyPothole

SEVERITY_COLOURS = {"low": "#f2c230", "moderate": "#f07d19", "high": "#d7261e"}
# the base map: Leaflet from its CDN, loaded only where the page is online; offline the
# route's drawing stays
LEAFLET_URL = "https://unpkg.com/leaflet@1.9.4/dist/"
# the most route points a map draws (the route is thinned to them)
MAP_ROUTE_POINTS = 2000
_MAP = """
(function () {
  var maps = document.querySelectorAll("div.map");
  if (!maps.length) return;
  var css = document.createElement("link");
  css.rel = "stylesheet"; css.href = LEAFLET + "leaflet.css";
  document.head.appendChild(css);
  var js = document.createElement("script");
  js.src = LEAFLET + "leaflet.js";
  js.onload = function () {
    maps.forEach(function (div) {
      var d = JSON.parse(div.dataset.map);
      div.style.display = "block";
      div.nextElementSibling.style.display = "none";
      var map = L.map(div);
      L.tileLayer(d.tiles, {maxZoom: 22, maxNativeZoom: 19, attribution: d.attribution})
        .addTo(map);
      var line = L.polyline(d.route, {color: "#3d6fb6", weight: 4}).addTo(map);
      d.potholes.forEach(function (p) {
        if (p.outline.length > 2)
          L.polygon(p.outline, {color: "#222", weight: 1, fillColor: p.colour,
                                fillOpacity: 0.6}).addTo(map);
        L.circleMarker([p.lat, p.lon], {radius: 6, color: "#222", weight: 1,
                                        fillColor: p.colour, fillOpacity: 1})
          .bindTooltip("#" + p.id + " " + p.label).addTo(map);
      });
      map.fitBounds(line.getBounds().pad(0.1));
    });
  };
  document.head.appendChild(js);
})();
"""
_STYLE = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1200px}
h1{margin:0 0 4px}h2{margin-top:28px}.muted{color:#666}
.cards{display:flex;gap:16px;flex-wrap:wrap}.card{border:1px solid #ddd;border-radius:8px;
padding:10px 14px}.card b{font-size:1.6em;display:block}
table{border-collapse:collapse;width:100%;font-size:.9em}th,td{border-bottom:1px solid #e4e4e4;
padding:4px 8px;text-align:right}th{cursor:pointer;background:#f6f6f6;position:sticky;top:0}
td.l,th.l{text-align:left}figure img{border-radius:4px;display:block}
.sev{display:inline-block;padding:1px 8px;border-radius:10px;color:#fff}
.gallery{display:flex;flex-wrap:wrap;gap:12px}.gallery figure{margin:0;font-size:.85em}
svg.drawing{background:#fafafa;border:1px solid #e4e4e4;border-radius:6px}
"""
_SORT = """
document.querySelectorAll('th').forEach((th,i)=>th.addEventListener('click',()=>{
const t=th.closest('table'),b=t.tBodies[0],r=[...b.rows],up=th.dataset.up!=='1';
r.sort((x,y)=>{const a=x.cells[i].dataset.v??x.cells[i].textContent,
c=y.cells[i].dataset.v??y.cells[i].textContent,n=parseFloat(a)-parseFloat(c);
return (isNaN(n)?a.localeCompare(c):n)*(up?1:-1)});
th.dataset.up=up?'1':'0';r.forEach(x=>b.appendChild(x))}));
"""


def _png(image: np.ndarray) -> str:
    ok, data = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode() if ok else ""


def _route_svg(drive: DriveSurvey, width: int = 560, height: int = 360) -> str:
    """The route (motion frame, or east/north where GNSS aligns it) and the potholes."""
    use_gnss = drive.route_latlon is not None and all(
        p.row["lat"] is not None for p in drive.potholes)
    if use_gnss:
        lat0 = float(drive.route_latlon[0, 0])
        scale = np.array([math.cos(math.radians(lat0)), 1.0]) * 111_320.0

        def xy(latlon: np.ndarray) -> np.ndarray:
            return (latlon[:, ::-1] - drive.route_latlon[0, ::-1]) * scale
        route = xy(drive.route_latlon)
        holes = xy(np.array([[p.row["lat"], p.row["lon"]] for p in drive.potholes])
                   .reshape(-1, 2))
        axes = "east / north (m, from GNSS)"

        def outline_xy(pothole: SurveyPothole) -> np.ndarray:
            return xy(pothole.outline_latlon) if len(pothole.outline_latlon) \
                else np.zeros((0, 2))
    else:
        route = drive.route_xy
        holes = np.array([[p.row["odom_x_m"], p.row["odom_y_m"]] for p in drive.potholes]
                         ).reshape(-1, 2)
        axes = f"x / y (m, motion frame: {drive.motion_source})"

        def outline_xy(pothole: SurveyPothole) -> np.ndarray:
            return pothole.outline_xy
    failed = np.array([[x, y] for _, _, x, y, _ in drive.failures
                       if math.isfinite(x) and math.isfinite(y)]).reshape(-1, 2)
    if use_gnss:
        failed = np.zeros((0, 2))  # their positions are in the motion frame only
    points = np.concatenate([route, holes, failed])
    if not len(points):
        return "<p class=muted>no route</p>"
    low, high = points.min(axis=0), points.max(axis=0)
    span = max(float((high - low).max()), 1.0)
    margin = 30

    def to_svg(p: np.ndarray) -> np.ndarray:
        q = (p - (low + high) / 2) / span * (min(width, height) - 2 * margin)
        return np.stack([width / 2 + q[:, 0], height / 2 - q[:, 1]], axis=-1)

    parts = [f'<svg class="drawing" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" role="img" aria-label="route">']
    if len(route):
        path = " ".join(f"{x:.1f},{y:.1f}" for x, y in to_svg(route))
        parts.append(f'<polyline points="{path}" fill="none" stroke="#3d6fb6" '
                     f'stroke-width="3" stroke-linecap="round"/>')
        sx, sy = to_svg(route[:1])[0]
        parts.append(f'<circle cx="{sx:.1f}" cy="{sy:.1f}" r="5" fill="#3d6fb6"/>'
                     f'<text x="{sx + 8:.1f}" y="{sy + 4:.1f}" font-size="11">start</text>')
    for x, y in to_svg(failed) if len(failed) else ():
        parts.append(f'<path d="M{x - 4:.1f},{y - 4:.1f}L{x + 4:.1f},{y + 4:.1f}M{x - 4:.1f},'
                     f'{y + 4:.1f}L{x + 4:.1f},{y - 4:.1f}" stroke="#888" stroke-width="2">'
                     '<title>a frame that failed</title></path>')
    for pothole in drive.potholes:
        outline = outline_xy(pothole)
        if len(outline) >= 3:
            corners = " ".join(f"{x:.1f},{y:.1f}" for x, y in to_svg(outline))
            parts.append(f'<polygon points="{corners}" fill="'
                         f'{SEVERITY_COLOURS[pothole.row["severity"]]}" stroke="#222" '
                         'stroke-width="1" opacity="0.8"/>')
    for pothole, (x, y) in zip(drive.potholes, to_svg(holes)):
        colour = SEVERITY_COLOURS[pothole.row["severity"]]
        parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="7" fill="{colour}" '
                     f'stroke="#222"><title>#{pothole.row["pothole_id"]} '
                     f'{pothole.row["max_depth_m"] * 1000:.0f} mm</title></circle>'
                     f'<text x="{x + 9:.1f}" y="{y - 7:.1f}" font-size="11">'
                     f'{pothole.row["pothole_id"]}</text>')
    crosses = "; grey crosses: frames that failed" if len(failed) else ""
    parts.append(f'<text x="8" y="{height - 8}" font-size="11" fill="#666">{axes}; '
                 f'{span:.1f} m across{crosses}</text></svg>')
    return "".join(parts)


def _failures_html(surveys: Sequence[DriveSurvey]) -> str:
    """Per bag, the frames that failed by kind of reason (how many, the first one's reason,
    seconds into the drive of the first), and the bags that could not be read."""
    rows = []
    for drive in surveys:
        name = html.escape(drive.bag.name)
        if drive.error:
            rows.append(f"<tr><td class=l>{name}</td><td>-</td><td class=l>not read: "
                        f"{html.escape(drive.error)}</td><td>-</td></tr>")
            continue
        start = drive.failures[0][0] - int(drive.failures[0][1] * 1e9) if drive.failures else 0
        for count, reason, stamp in drive.failure_tally().rows():
            rows.append(f"<tr><td class=l>{name}</td><td>{count}</td><td class=l>"
                        f"{html.escape(reason)}</td><td>{(stamp - start) / 1e9:.1f}</td></tr>")
    if not rows:
        return "<p class=muted>Every frame was processed.</p>"
    return ("<table id=failures><thead><tr><th class=l>bag</th><th>frames</th>"
            "<th class=l>why (the first such frame's reason)</th><th>first at s</th></tr>"
            "</thead><tbody>" + "".join(rows) + "</tbody></table>")


def _histogram_svg(values: Sequence[float], label: str, unit_scale: float, unit: str,
                   bins: int = 10, width: int = 360, height: int = 200) -> str:
    if not values:
        return ""
    scaled = np.asarray(values, dtype=np.float64) * unit_scale
    counts, edges = np.histogram(scaled, bins=bins)
    top = max(int(counts.max()), 1)
    bar = (width - 40) / bins
    parts = [f'<svg class="drawing" width="{width}" height="{height}" role="img" '
             f'aria-label="{label}">']
    for i, count in enumerate(counts):
        h = (height - 50) * count / top
        parts.append(f'<rect x="{30 + i * bar:.1f}" y="{height - 30 - h:.1f}" '
                     f'width="{bar - 2:.1f}" height="{h:.1f}" fill="#3d6fb6">'
                     f'<title>{edges[i]:.1f}-{edges[i + 1]:.1f} {unit}: {count}</title></rect>')
    parts.append(f'<text x="30" y="{height - 14}" font-size="11">{edges[0]:.1f}</text>'
                 f'<text x="{width - 40}" y="{height - 14}" font-size="11">{edges[-1]:.1f}'
                 f'</text><text x="30" y="14" font-size="12">{html.escape(label)} ({unit}), '
                 f'{len(values)} potholes, most in one bin {top}</text></svg>')
    return "".join(parts)


def _row_html(pothole: SurveyPothole) -> str:
    r = pothole.row
    colour = SEVERITY_COLOURS[r["severity"]]
    low, high = pothole.depth_spread_m
    cells = [
        (str(r["pothole_id"]), r["pothole_id"], ""), (html.escape(r["bag"]), None, "l"),
        (f'<span class="sev" style="background:{colour}">{r["severity"]}</span>',
         SEVERITIES.index(r["severity"]), "l"),
        (f'{r["max_depth_m"] * 1000:.0f} <span class=muted>({low * 1000:.0f}-'
         f'{high * 1000:.0f})</span>', r["max_depth_m"], ""),
        (f'{r["mean_depth_m"] * 1000:.0f}', r["mean_depth_m"], ""),
        (f'{r["area_m2"] * 1e4:.0f}', r["area_m2"], ""),
        (f'{r["length_m"] * 100:.0f} x {r["width_m"] * 100:.0f}'
         if math.isfinite(r["length_m"]) and math.isfinite(r["width_m"]) else "-",
         r["length_m"] if math.isfinite(r["length_m"]) else "", ""),
        (f'{r["volume_m3"] * 1e6:.0f}', r["volume_m3"], ""),
        (str(r["sightings"]), r["sightings"], ""),
        (f'{r["odom_x_m"]:.2f}, {r["odom_y_m"]:.2f}', r["odom_x_m"], ""),
        (f'{r["lat"]:.7f}, {r["lon"]:.7f}' if r["lat"] is not None else "-",
         r["lat"] if r["lat"] is not None else "", ""),
        (html.escape(r["best_time_utc"]), r["best_stamp_ns"], ""),
    ]
    return "<tr>" + "".join(
        f'<td class="{cls}"' + (f' data-v="{value}"' if value is not None else "")
        + f">{text}</td>" for text, value, cls in cells) + "</tr>"


def _map_div(drive: DriveSurvey, tiles: tuple[str, str]) -> str:
    """A drive's base map (hidden until Leaflet loads, then shown in place of the route's
    drawing that follows it): the route, the potholes and their outlines in lat/lon, the
    tiles ``(URL template, attribution)``; empty without GNSS."""
    if drive.route_latlon is None or not len(drive.route_latlon):
        return ""
    step = max(1, -(-len(drive.route_latlon) // MAP_ROUTE_POINTS))
    route = np.concatenate([drive.route_latlon[::step], drive.route_latlon[-1:]])
    potholes = [{"id": p.row["pothole_id"], "lat": p.row["lat"], "lon": p.row["lon"],
                 "colour": SEVERITY_COLOURS[p.row["severity"]],
                 "label": f'{p.row["severity"]}, {p.row["max_depth_m"] * 1000:.0f} mm',
                 "outline": np.round(p.outline_latlon, 8).tolist()}
                for p in drive.potholes if p.row["lat"] is not None]
    data = {"route": np.round(route, 8).tolist(), "potholes": potholes, "tiles": tiles[0],
            "attribution": tiles[1]}
    return (f'<div class=map style="display:none;height:420px;max-width:900px" '
            f'data-map="{html.escape(json.dumps(data))}"></div>')


def write_report(surveys: Sequence[DriveSurvey], path: str | Path,
                 picture: Callable[[DriveSurvey, SurveyPothole], np.ndarray | None],
                 tiles: tuple[str, str] = (
                     PARAMETER_BY_NAME["report_tiles_url"].default,
                     PARAMETER_BY_NAME["report_tiles_attribution"].default)) -> None:
    """Write report.html for ``surveys``; ``picture(drive, pothole)`` gives the best-view
    crop (HxWx3 RGB) of a pothole, or None. Where the page is online, drives with GNSS are
    drawn over a base map of ``tiles`` (a Leaflet URL template and its attribution); offline
    the route's drawing stays."""
    potholes = [p for drive in surveys for p in drive.potholes]
    counts = {s: sum(p.row["severity"] == s for p in potholes) for s in SEVERITIES}
    observed = sum(d.observed_length_m for d in surveys)
    frames = sum(d.frames for d in surveys)
    failed = sum(d.failed for d in surveys)
    cards = [("potholes", str(len(potholes))),
             *((f"{s} severity", str(counts[s])) for s in SEVERITIES),
             ("road observed", f"{observed:.1f} m"), ("frames", str(frames)),
             ("frames failed", str(failed)), ("bags", str(len(surveys)))]
    header = ("<tr><th>id</th><th class=l>bag</th><th class=l>severity</th>"
              "<th>max depth mm (spread)</th><th>mean depth mm</th><th>area cm²</th>"
              "<th>length x width cm</th><th>volume cm³</th><th>sightings</th>"
              "<th>position x, y m</th><th>lat, lon</th><th>best view (UTC)</th></tr>")
    gallery = []
    for drive in surveys:
        for pothole in drive.potholes:
            image = picture(drive, pothole)
            if image is None:
                continue
            r = pothole.row
            gallery.append(f'<figure><img src="{_png(image)}" alt="pothole {r["pothole_id"]}">'
                           f'<figcaption>#{r["pothole_id"]} {r["severity"]}, '
                           f'{r["max_depth_m"] * 1000:.0f} mm, {r["area_m2"] * 1e4:.0f} cm²'
                           f'</figcaption></figure>')
    routes = "".join(f"<h3>{html.escape(d.bag.name)}</h3>{_map_div(d, tiles)}"
                     f"<div>{_route_svg(d)}</div>" for d in surveys)
    standards = sorted({p.row["severity_standard"] for p in potholes}) or ["ltpp"]
    standard = " / ".join({"ltpp": "largest depth (FHWA LTPP)",
                           "astm_d6433": "largest depth and diameter (ASTM D6433)"}[s]
                          for s in standards)
    legend = " ".join(f'<span class="sev" style="background:{SEVERITY_COLOURS[s]}">{s}</span>'
                      for s in SEVERITIES)
    page = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Pothole survey</title>
<style>{_STYLE}</style></head><body>
<h1>Pothole survey</h1>
<p class=muted>{len(surveys)} drive(s); severity by {standard}: {legend}</p>
<div class=cards>{"".join(f"<div class=card><b>{v}</b>{k}</div>" for k, v in cards)}</div>
<h2>Route</h2>{routes}
<h2>Potholes</h2><p class=muted>Click a column to sort.</p>
<table id=potholes><thead>{header}</thead><tbody>
{"".join(_row_html(p) for p in potholes)}
</tbody></table>
<h2>Best views</h2><div class=gallery>{"".join(gallery)}</div>
<h2>Depths and sizes</h2>
{_histogram_svg([p.row["max_depth_m"] for p in potholes], "largest depth", 1000, "mm")}
{_histogram_svg([p.row["area_m2"] for p in potholes], "area", 1e4, "cm²")}
<h2>Frames that failed</h2>{_failures_html(surveys)}
<script>{_SORT}</script>
<script>var LEAFLET = "{LEAFLET_URL}";{_MAP}</script></body></html>
"""
    Path(path).write_text(page, encoding="utf-8")
