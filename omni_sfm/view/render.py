"""A results folder as a PNG snapshot (matplotlib), an offline HTML page and Open3D line sets.

Open3D's offscreen renderer needs an EGL/Vulkan-capable GPU driver, which a headless CPU machine
lacks ("Failed to load vulkan library" here), so the snapshot is drawn with matplotlib's 3D axes.
The HTML page carries its data (base64 float32 / uint8 arrays) and its own canvas-2D renderer
(z-buffered points, lines on top, orbit by dragging, zoom by the wheel): no CDN, nothing fetched.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omni_sfm.export.open3d import (
    camera_segments,
    cameras_line_set,
    group_colors,
    lines3d_line_set,
    write_line_set,
)
from omni_sfm.fileio import atomic_write_text
from omni_sfm.folders import DenseFolder
from omni_sfm.view.scene import ViewScene, load_view_scene, upright_from_world

HTML_MAX_POINTS = 150_000
PNG_MAX_POINTS = 60_000
AXES_DRAWN = 15


@dataclass(frozen=True)
class ViewOutputs:
    """Files written by :func:`make_view` (``lines3d`` is None without 3D lines)."""

    png: Path
    html: Path
    cameras: Path
    lines3d: Path | None


def _axis_settings(scene: ViewScene) -> tuple[float, int]:
    """Axis length and pose step for the camera axes drawn (about ``AXES_DRAWN`` poses)."""
    n = len(scene.trajectory)
    return 0.02 * scene.extent(), max(1, n // AXES_DRAWN)


def _subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def write_png(scene: ViewScene, path: Path, *, title: str = "") -> None:
    """Matplotlib 3D snapshot: dense points, 3D lines by parallel group, path, camera axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    R = upright_from_world(scene.up)
    fig = plt.figure(figsize=(10, 7.5), dpi=100)
    ax = fig.add_subplot(projection="3d")
    keep = _subsample(len(scene.points), PNG_MAX_POINTS)
    if keep.size:
        p = scene.points[keep] @ R.T
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=scene.colors[keep], s=2.0, marker=".",
                   linewidths=0, depthshade=False)
    if len(scene.line_starts):
        segs = np.stack([scene.line_starts @ R.T, scene.line_ends @ R.T], axis=1)
        ax.add_collection3d(Line3DCollection(segs, colors=group_colors(scene.line_groups),
                                             linewidths=1.6))
    length, every = _axis_settings(scene)
    s, e, c = camera_segments(scene.trajectory, length, every)
    ax.add_collection3d(Line3DCollection(np.stack([s @ R.T, e @ R.T], axis=1), colors=c,
                                         linewidths=1.2))
    allp = np.concatenate([scene.trajectory.positions, scene.line_starts, scene.line_ends,
                           scene.points[keep]]) @ R.T
    lo, hi = np.percentile(allp, 0.5, axis=0), np.percentile(allp, 99.5, axis=0)
    mid, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-9)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=35, azim=-60)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("up")
    ax.set_title(title or "omni-sfm", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)


def _b64(a: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def html_document(scene: ViewScene, *, title: str = "omni-sfm") -> str:
    """The self-contained page (see the module docstring); coordinates upright (+z up)."""
    R = upright_from_world(scene.up)
    keep = _subsample(len(scene.points), HTML_MAX_POINTS)
    pts = scene.points[keep] @ R.T
    length, every = _axis_settings(scene)
    cs, ce, cc = camera_segments(scene.trajectory, length, every)
    ls, le = scene.line_starts @ R.T, scene.line_ends @ R.T
    segs = np.concatenate([np.hstack([ls, le]), np.hstack([cs @ R.T, ce @ R.T])])
    seg_cols = np.concatenate([group_colors(scene.line_groups), cc])
    widths = np.r_[np.full(len(ls), 2.0), np.full(len(cs), 1.2)]
    allp = np.concatenate([scene.trajectory.positions @ R.T, ls, le, pts])
    lo, hi = np.percentile(allp, 1, axis=0), np.percentile(allp, 99, axis=0)
    data = {
        "points": _b64(pts, "<f4"), "colors": _b64(np.rint(255 * scene.colors[keep]), "u1"),
        "segments": _b64(segs, "<f4"), "segColors": _b64(np.rint(255 * seg_cols), "u1"),
        "segWidths": widths.tolist(), "center": ((lo + hi) / 2).tolist(),
        "radius": max(float(np.linalg.norm(hi - lo)) / 2, 1e-9),
        "caption": title,
    }
    return (_HTML.replace("__TITLE__", _escape(title))
            .replace("__DATA__", json.dumps(data).replace("</", "<\\/")))


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def write_html(scene: ViewScene, path: Path, *, title: str = "omni-sfm") -> None:
    atomic_write_text(path, html_document(scene, title=title))


def caption(scene: ViewScene, folder: Path) -> str:
    return (f"{folder.name}: {len(scene.trajectory)} poses, {len(scene.line_starts)} 3D lines, "
            f"{len(scene.points)} dense points shown")


def make_view(folder: Path, output: Path | None = None) -> ViewOutputs:
    """Read ``folder`` (:func:`load_view_scene`) and write the PNG (``output``, default
    ``folder/view.png``), the HTML page beside it (same name, ``.html``), ``cameras.ply`` and,
    with 3D lines, ``lines3d.ply`` in the PNG's folder."""
    folder = Path(folder)
    scene = load_view_scene(folder)
    png = Path(output) if output is not None else folder / DenseFolder.VIEW_PNG
    if png.suffix.lower() != ".png":
        png = png.with_suffix(".png")
    png.parent.mkdir(parents=True, exist_ok=True)
    title = caption(scene, folder)
    write_png(scene, png, title=title)
    html = png.with_suffix(".html")
    write_html(scene, html, title=title)
    length, every = _axis_settings(scene)
    cams = png.parent / "cameras.ply"
    write_line_set(cams, cameras_line_set(scene.trajectory, length, every))
    lines = None
    if len(scene.line_starts):
        lines = png.parent / "lines3d.ply"
        write_line_set(lines, lines3d_line_set(scene.line_starts, scene.line_ends,
                                               scene.line_groups))
    return ViewOutputs(png, html, cams, lines)


_HTML = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>__TITLE__</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
html, body { margin: 0; height: 100%; overflow: hidden; background: #f4f4f2;
  font: 13px sans-serif; }
#view { display: block; width: 100%; height: 100%; cursor: grab; }
#info { position: absolute; left: 8px; top: 6px; color: #333; background: rgba(255,255,255,.7);
  padding: 3px 6px; border-radius: 3px; }
</style></head>
<body>
<canvas id="view"></canvas>
<div id="info"><span id="caption"></span><br>drag: orbit, shift-drag or right-drag: pan,
wheel: zoom, double-click: reset. <span id="status">loading</span></div>
<script>
"use strict";
(function () {
  var D = __DATA__;
  function decode(s, T) {
    var bin = atob(s), u = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i);
    return new T(u.buffer);
  }
  var P = decode(D.points, Float32Array), C = decode(D.colors, Uint8Array);
  var S = decode(D.segments, Float32Array), SC = decode(D.segColors, Uint8Array);
  var nP = P.length / 3, nS = S.length / 6;
  var canvas = document.getElementById("view"), ctx = canvas.getContext("2d");
  document.getElementById("caption").textContent = D.caption;
  var st;
  function reset() {
    st = { yaw: -2.2, pitch: 0.6, dist: 1.7 * D.radius, c: D.center.slice() };
  }
  reset();
  function basis() {
    var cp = Math.cos(st.pitch), sp = Math.sin(st.pitch);
    var cy = Math.cos(st.yaw), sy = Math.sin(st.yaw);
    var back = [cp * cy, cp * sy, sp];
    var eye = [st.c[0] + st.dist * back[0], st.c[1] + st.dist * back[1],
               st.c[2] + st.dist * back[2]];
    var fwd = [-back[0], -back[1], -back[2]];
    var right = [-sy, cy, 0];
    var up = [right[1] * fwd[2] - right[2] * fwd[1], right[2] * fwd[0] - right[0] * fwd[2],
              right[0] * fwd[1] - right[1] * fwd[0]];
    return { eye: eye, fwd: fwd, right: right, up: up };
  }
  var pending = false;
  function request() { if (!pending) { pending = true; requestAnimationFrame(draw); } }
  function draw() {
    pending = false;
    var W = canvas.width = canvas.clientWidth, H = canvas.height = canvas.clientHeight;
    if (W < 2 || H < 2) return;
    var b = basis(), f = 0.9 * Math.min(W, H), near = 1e-3 * D.radius;
    var img = ctx.createImageData(W, H), px = img.data, zb = new Float32Array(W * H);
    for (var i = 0; i < W * H; i++) {
      zb[i] = Infinity; px[4 * i] = 244; px[4 * i + 1] = 244; px[4 * i + 2] = 242;
      px[4 * i + 3] = 255;
    }
    var ex = b.eye[0], ey = b.eye[1], ez = b.eye[2], drawn = 0;
    for (var k = 0; k < nP; k++) {
      var x = P[3 * k] - ex, y = P[3 * k + 1] - ey, z = P[3 * k + 2] - ez;
      var zc = x * b.fwd[0] + y * b.fwd[1] + z * b.fwd[2];
      if (zc <= near) continue;
      var u = Math.round(W / 2 + f * (x * b.right[0] + y * b.right[1] + z * b.right[2]) / zc);
      var v = Math.round(H / 2 - f * (x * b.up[0] + y * b.up[1] + z * b.up[2]) / zc);
      if (u < 0 || v < 0 || u >= W - 1 || v >= H - 1) continue;
      for (var dv = 0; dv < 2; dv++) for (var du = 0; du < 2; du++) {
        var q = (v + dv) * W + u + du;
        if (zc < zb[q]) {
          zb[q] = zc; px[4 * q] = C[3 * k]; px[4 * q + 1] = C[3 * k + 1];
          px[4 * q + 2] = C[3 * k + 2];
        }
      }
      drawn++;
    }
    ctx.putImageData(img, 0, 0);
    var lines = 0;
    function proj(x, y, z) {
      x -= ex; y -= ey; z -= ez;
      var zc = x * b.fwd[0] + y * b.fwd[1] + z * b.fwd[2];
      return [x * b.right[0] + y * b.right[1] + z * b.right[2],
              x * b.up[0] + y * b.up[1] + z * b.up[2], zc];
    }
    for (var s = 0; s < nS; s++) {
      var a = proj(S[6 * s], S[6 * s + 1], S[6 * s + 2]);
      var e = proj(S[6 * s + 3], S[6 * s + 4], S[6 * s + 5]);
      if (a[2] <= near && e[2] <= near) continue;
      if (a[2] <= near || e[2] <= near) {  // clip at the near plane
        var t = (near - a[2]) / (e[2] - a[2]), m = [a[0] + t * (e[0] - a[0]),
          a[1] + t * (e[1] - a[1]), near];
        if (a[2] <= near) a = m; else e = m;
      }
      ctx.strokeStyle = "rgb(" + SC[3 * s] + "," + SC[3 * s + 1] + "," + SC[3 * s + 2] + ")";
      ctx.lineWidth = D.segWidths[s];
      ctx.beginPath();
      ctx.moveTo(W / 2 + f * a[0] / a[2], H / 2 - f * a[1] / a[2]);
      ctx.lineTo(W / 2 + f * e[0] / e[2], H / 2 - f * e[1] / e[2]);
      ctx.stroke();
      lines++;
    }
    document.getElementById("status").textContent =
      "drawn: " + drawn + " points, " + lines + " segments";
    document.body.setAttribute("data-drawn", String(drawn + lines));
  }
  var drag = null;
  canvas.addEventListener("contextmenu", function (ev) { ev.preventDefault(); });
  canvas.addEventListener("pointerdown", function (ev) {
    drag = { x: ev.clientX, y: ev.clientY, pan: ev.shiftKey || ev.button === 2 };
    canvas.setPointerCapture(ev.pointerId);
  });
  canvas.addEventListener("pointerup", function () { drag = null; });
  canvas.addEventListener("pointermove", function (ev) {
    if (!drag) return;
    var dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
    drag.x = ev.clientX; drag.y = ev.clientY;
    if (drag.pan) {
      var b = basis(), k = st.dist / (0.9 * Math.min(canvas.width, canvas.height));
      for (var i = 0; i < 3; i++) st.c[i] += k * (-dx * b.right[i] + dy * b.up[i]);
    } else {
      st.yaw -= 0.008 * dx;
      st.pitch = Math.max(-1.55, Math.min(1.55, st.pitch + 0.008 * dy));
    }
    request();
  });
  canvas.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    st.dist *= Math.exp(0.0015 * ev.deltaY);
    request();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { reset(); request(); });
  window.addEventListener("resize", request);
  draw();
})();
</script>
</body></html>
"""
