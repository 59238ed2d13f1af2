"use strict";
// Line charts on a canvas: labelled axes with ticks, reference lines and markers, a legend.

const charts = (() => {
  const FONT = "system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif";

  /** About `count` round tick values covering [lo, hi]. */
  function ticks(lo, hi, count) {
    const raw = (hi - lo) / Math.max(count, 1);
    const power = 10 ** Math.floor(Math.log10(raw));
    const step = [1, 2, 2.5, 5, 10].map((m) => m * power).find((s) => s >= raw) || raw;
    const values = [];
    for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + 1e-9 * step; v += step) {
      values.push(Math.round(v / step) * step);
    }
    return {values, step};
  }

  /** A tick value with no more decimals than it needs (at most 3). */
  function label(value) {
    return String(Number(value.toFixed(3)));
  }

  /**
   * Draw a chart. spec: {title, xLabel, yLabel, x: [min, max], y: [min, max],
   * lines: [{points: [[x, y]], colour, label}], refs: [{y, colour, label}] (dashed horizontal
   * lines), marks: [{x, colour}] (vertical lines), keys: [{colour, label, dashed}] (extra
   * legend entries), empty: text shown when there is nothing to plot}.
   */
  function draw(canvas, spec) {
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth;
    const height = canvas.clientHeight;
    if (canvas.width !== Math.round(width * ratio)) canvas.width = Math.round(width * ratio);
    if (canvas.height !== Math.round(height * ratio)) canvas.height = Math.round(height * ratio);
    const g = canvas.getContext("2d");
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.clearRect(0, 0, width, height);
    const box = {left: 62, right: width - 14, top: 30, bottom: height - 42};
    const [x0, x1] = spec.x;
    const [y0, y1] = spec.y;
    const px = (x) => box.left + ((x - x0) / (x1 - x0 || 1)) * (box.right - box.left);
    const py = (y) => box.bottom - ((y - y0) / (y1 - y0 || 1)) * (box.bottom - box.top);

    g.fillStyle = "#1b1f24";
    g.font = `600 14px ${FONT}`;
    g.textAlign = "left";
    g.textBaseline = "alphabetic";
    g.fillText(spec.title, box.left, 18);

    // Grid, ticks and tick labels.
    g.font = `12px ${FONT}`;
    g.strokeStyle = "#e3e6ea";
    g.lineWidth = 1;
    const xt = ticks(x0, x1, Math.max(2, Math.floor((box.right - box.left) / 80)));
    const yt = ticks(y0, y1, Math.max(2, Math.floor((box.bottom - box.top) / 24)));
    g.fillStyle = "#4a525c";
    g.textAlign = "center";
    g.textBaseline = "top";
    for (const v of xt.values) {
      g.beginPath(); g.moveTo(px(v), box.top); g.lineTo(px(v), box.bottom); g.stroke();
      g.fillText(label(v), px(v), box.bottom + 5);
    }
    g.textAlign = "right";
    g.textBaseline = "middle";
    for (const v of yt.values) {
      g.beginPath(); g.moveTo(box.left, py(v)); g.lineTo(box.right, py(v)); g.stroke();
      g.fillText(label(v), box.left - 6, py(v));
    }
    g.strokeStyle = "#8a929c";
    g.strokeRect(box.left, box.top, box.right - box.left, box.bottom - box.top);

    // Axis labels.
    g.fillStyle = "#1b1f24";
    g.font = `13px ${FONT}`;
    g.textAlign = "center";
    g.textBaseline = "bottom";
    g.fillText(spec.xLabel, (box.left + box.right) / 2, height - 4);
    g.save();
    g.translate(14, (box.top + box.bottom) / 2);
    g.rotate(-Math.PI / 2);
    g.textBaseline = "middle";
    g.fillText(spec.yLabel, 0, 0);
    g.restore();

    // Data, clipped to the plot area.
    g.save();
    g.beginPath();
    g.rect(box.left, box.top, box.right - box.left, box.bottom - box.top);
    g.clip();
    for (const mark of spec.marks || []) {
      g.strokeStyle = mark.colour;
      g.lineWidth = 2;
      g.beginPath(); g.moveTo(px(mark.x), box.top); g.lineTo(px(mark.x), box.bottom); g.stroke();
    }
    for (const ref of spec.refs || []) {
      g.strokeStyle = ref.colour;
      g.lineWidth = 1.5;
      g.setLineDash([6, 4]);
      g.beginPath(); g.moveTo(box.left, py(ref.y)); g.lineTo(box.right, py(ref.y)); g.stroke();
      g.setLineDash([]);
    }
    for (const line of spec.lines) {
      g.strokeStyle = line.colour;
      g.lineWidth = 2;
      g.lineJoin = "round";
      g.beginPath();
      line.points.forEach(([x, y], i) => (i ? g.lineTo(px(x), py(y)) : g.moveTo(px(x), py(y))));
      g.stroke();
      if (line.points.length === 1) {
        const [x, y] = line.points[0];
        g.fillStyle = line.colour;
        g.beginPath(); g.arc(px(x), py(y), 2.5, 0, 2 * Math.PI); g.fill();
      }
    }
    g.restore();
    if (spec.empty && !spec.lines.some((line) => line.points.length)) {
      g.fillStyle = "#8a929c";
      g.font = `13px ${FONT}`;
      g.textAlign = "center";
      g.textBaseline = "middle";
      g.fillText(spec.empty, (box.left + box.right) / 2, (box.top + box.bottom) / 2);
    }

    // Legend, right-aligned above the plot.
    const keys = [
      ...spec.lines.map((line) => ({colour: line.colour, label: line.label})),
      ...(spec.refs || []).map((ref) => ({colour: ref.colour, label: ref.label, dashed: true})),
      ...(spec.keys || []),
    ];
    g.font = `12px ${FONT}`;
    g.textAlign = "left";
    g.textBaseline = "middle";
    let x = box.right;
    for (const key of keys.reverse()) {
      x -= g.measureText(key.label).width + 30;
      g.strokeStyle = key.colour;
      g.lineWidth = 2;
      g.setLineDash(key.dashed ? [5, 3] : []);
      g.beginPath(); g.moveTo(x, 15); g.lineTo(x + 18, 15); g.stroke();
      g.setLineDash([]);
      g.fillStyle = "#1b1f24";
      g.fillText(key.label, x + 22, 15);
    }
  }

  return {draw};
})();
