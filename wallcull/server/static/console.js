// wallcull's operator console (GET /walls/{wid}/console): the wall drawn to scale as it stands
// in the room, each tile coloured by its state and labelled with its list size and latency,
// updated from WS /walls/{wid}/console/stream (a status whenever it changes). Each tile, on the
// plan and in the table, links to its view page (the render node's page for that tile alone);
// the legend beside the table says what each colour means.
//
// A flat wall (a grid, or screens that all face +z) is drawn from the front: x right, y up.
// Screens around the viewer (a CAVE, angled walls) are drawn from above, their corners
// projected onto the floor plane: x right, z toward the viewer (down the page); the floor's
// screens are areas, the walls' are thick lines, labelled on the side they are seen from.
// Screens that stand in rows above each other (CAVE2's columns of four), which would hide each
// other from above, are unrolled instead: each at its angle around the viewer (x, left to
// right as the viewer turns right) and its height (y up), as a panorama of the room.
//
// A status is drawn once the browser draws: messages that came meanwhile are dropped, only the
// newest is parsed and shown (a 64 x 64 wall's took longer to draw than the next took to come,
// and the page fell ever further behind). A lost stream greys the plan and the table (the state
// shown is the last known), and the page asks the server why before it tries again.

const cfg = JSON.parse(document.getElementById("wallcull-config").textContent);
const SVG = "http://www.w3.org/2000/svg";
const plan = document.getElementById("plan"), body = document.querySelector("#tiles tbody");
const summary = document.getElementById("summary");
document.querySelector("h1 code").textContent = cfg.wall;
const api = window.wallcull = { updates: 0, received: 0, status: null };

const sub = (a, b) => a.map((x, i) => x - b[i]), add = (a, b) => a.map((x, i) => x + b[i]);
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => { const n = Math.hypot(...a) || 1; return a.map((x) => x / n); };

function screensOf(wall) {  // every tile as 4 corners in display space (SPEC 2, 2b)
  if (wall.screens) {
    return wall.screens.map((s) => [s.bottom_left, s.bottom_right,
                                    add(s.top_left, sub(s.bottom_right, s.bottom_left)), s.top_left]);
  }
  const [w, h] = wall.tile_size, [gx, gy] = wall.gap || [0, 0], z = -wall.distance;
  const W = wall.cols * w + (wall.cols - 1) * gx, H = wall.rows * h + (wall.rows - 1) * gy;
  const out = [];
  for (let t = 0; t < wall.cols * wall.rows; t++) {
    const r = Math.floor(t / wall.cols), c = t % wall.cols;
    const x0 = -W / 2 + c * (w + gx), y1 = H / 2 - r * (h + gy);
    out.push([[x0, y1 - h, z], [x0 + w, y1 - h, z], [x0 + w, y1, z], [x0, y1, z]]);
  }
  return out;
}

function el(name, attrs = {}, parent = null) {
  const e = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

// Whether screens seen from above share their place: walls (lines from above) in rows.
function stacked(flat, thin) {
  const seen = new Set();
  for (let t = 0; t < flat.length; t++) {
    if (!thin[t]) continue;
    const key = flat[t].map((p) => p.map((v) => Math.round(v * 100)).join(",")).sort().join(" ");
    if (seen.has(key)) return true;
    seen.add(key);
  }
  return false;
}

// A screen's corners unrolled around the viewer: [angle x mean distance, -height].
function unroller(corners) {
  let r = 0;
  for (const c of corners) r += Math.hypot((c[0][0] + c[1][0]) / 2, (c[0][2] + c[1][2]) / 2);
  r = r / corners.length || 1;
  return (c) => {
    const mid = c.reduce((m, p) => add(m, p), [0, 0, 0]), at = Math.atan2(mid[0], -mid[2]);
    return c.map((p) => {
      let a = Math.atan2(p[0], -p[2]) - at;
      a -= 2 * Math.PI * Math.round(a / (2 * Math.PI));  // on the screen's side of the cut
      return [(at + a) * r, -p[1]];
    });
  };
}

function drawPlan(wall) {
  const corners = screensOf(wall);
  const normals = corners.map((c) => unit(cross(sub(c[1], c[0]), sub(c[3], c[0]))));
  const facing = normals.every((n) => n[2] > 0.99);
  const project = facing ? (p) => [p[0], -p[1]] : (p) => [p[0], p[2]];
  let flat = corners.map((c) => c.map(project));
  const upright = normals.map((n) => Math.abs(n[1]) < 0.1);
  const around = !facing && stacked(flat, upright);
  if (around) flat = corners.map(unroller(corners));
  const front = facing || around;  // drawn as seen, not from above
  // the extent by a loop: spreading 4 values a tile as arguments threw past ~31,000 tiles
  let [x0, x1, y0, y1] = front ? [Infinity, -Infinity, Infinity, -Infinity] : [0, 0, 0, 0];
  for (const q of flat) {  // (from above, the viewer at the display origin is in it too)
    for (const [x, y] of q) {
      if (x < x0) x0 = x;
      if (x > x1) x1 = x;
      if (y < y0) y0 = y;
      if (y > y1) y1 = y;
    }
  }
  const extent = Math.max(x1 - x0, y1 - y0) || 1, pad = extent * 0.08;
  plan.dataset.layout = around ? "around" : facing ? "front" : "above";
  plan.setAttribute("viewBox", `${x0 - pad} ${y0 - pad} ${x1 - x0 + 2 * pad} ${y1 - y0 + 2 * pad}`);
  plan.replaceChildren();
  const area = (q) => Math.abs(q.reduce((s, p, i) => s + p[0] * q[(i + 1) % 4][1] - q[(i + 1) % 4][0] * p[1], 0)) / 2;
  const order = flat.map((q, t) => t).sort((a, b) => area(flat[b]) - area(flat[a]));  // floors first
  const groups = [];
  for (const t of order) {
    const link = el("a", { href: viewOf(t) }, plan);
    const q = flat[t], g = el("g", { class: "tile offline", id: `tile-${t}`, "data-tile": t }, link);
    el("title", {}, g).textContent = `tile ${t}: open its view`;
    const thin = area(q) < 1e-3 * extent * extent;
    el("polygon", { points: q.map((p) => p.join(",")).join(" "), class: thin ? "thin" : "",
                    "stroke-width": thin ? extent * 0.02 : extent * 0.002 }, g);
    let [cx, cy] = [q.reduce((s, p) => s + p[0], 0) / 4, q.reduce((s, p) => s + p[1], 0) / 4];
    const edge = Math.min(Math.hypot(...sub(q[1], q[0])), Math.hypot(...sub(q[3], q[0])));
    const size = front ? edge * 0.2 : extent * 0.03;
    if (thin) {  // a wall seen from above: its label on the side it faces
      const n = project(normals[t]), k = Math.hypot(...n) || 1;
      [cx, cy] = [cx + n[0] / k * extent * 0.07, cy + n[1] / k * extent * 0.07];
    } else if (!front) {
      cy += 3 * size;  // a floor or a ceiling: clear of the viewer, at the origin
    }
    const text = (cls, dy, value) => {
      const e = el("text", { class: cls, x: cx, y: cy + dy * size, "font-size": size }, g);
      e.textContent = value;
      return e;
    };
    groups[t] = { g, name: text("name", -1.1, `#${t}`), count: text("count", 0, "-"),
                  latency: text("latency", 1.1, "") };
  }
  if (!front) {
    el("circle", { class: "viewer", cx: 0, cy: 0, r: extent * 0.012 }, plan);
  }
  return groups;
}

// A tile's view page: the tile client drawing that tile alone (with a server token, it needs
// the tile's node credential or the operator's: the console's own ?token= is passed on).
const viewOf = (t) => `${cfg.root}/walls/${cfg.wall}/view?tiles=${t}` +
  (cfg.token ? `&token=${encodeURIComponent(cfg.token)}` : "");

function fillTable(n) {
  body.replaceChildren();
  const rows = [];
  for (let t = 0; t < n; t++) {
    const tr = document.createElement("tr");
    tr.id = `row-${t}`;
    for (let k = 0; k < 6; k++) tr.appendChild(document.createElement("td"));
    const a = document.createElement("a");
    a.href = viewOf(t);
    a.textContent = t;
    tr.cells[0].appendChild(a);
    body.appendChild(tr);
    rows.push(tr);
  }
  return rows;
}

// What each tile shows, so that a status writes only what changed: rewriting all of a
// 64 x 64 wall's 4,096 rows and plan tiles took 0.7 s of the page's thread a status, with
// nothing changed.
const shown = [];
const put = (t, key, v, write) => {
  const was = shown[t] || (shown[t] = {});
  if (was[key] !== v) { was[key] = v; write(v); }
};

function show(groups, rows, s) {
  const ms = (v) => (v === null ? "" : `${v.toFixed(1)} ms`);
  s.count.forEach((count, t) => {
    const state = s.state[t], latency = ms(s.latency_ms[t]), cells = rows[t].cells;
    put(t, "state", state, (v) => { groups[t].g.setAttribute("class", `tile ${v}`); rows[t].className = v; });
    put(t, "leaves", `${count} ${count === 1 ? "leaf" : "leaves"}`, (v) => { groups[t].count.textContent = v; });
    put(t, "label", s.ack[t] >= 0 ? `#${s.ack[t]} ${latency}` : state, (v) => { groups[t].latency.textContent = v; });
    [count, s.ack[t], latency, s.streams[t], state].forEach((v, k) => put(t, k, v, (w) => { cells[k + 1].textContent = w; }));
  });
  let acked = 0;
  for (const x of s.state) if (x === "acked") acked += 1;
  const age = s.posted === null ? "" : `, posted ${(s.time - s.posted).toFixed(1)} s ago`;
  summary.textContent = s.frame >= 0 ?
    `frame ${s.frame}${age}; ${acked} of ${s.count.length} tiles have drawn it` :
    s.newest >= 0 ? `frame ${s.newest} before the server restarted; none since` : "no frame yet";
  api.status = s;
  api.updates += 1;
}

async function start() {
  const r = await fetch(`${cfg.root}/walls/${cfg.wall}`);
  if (!r.ok) { summary.textContent = `no wall ${cfg.wall} (HTTP ${r.status})`; return; }
  const info = await r.json();
  const groups = drawPlan(info.wall), rows = fillTable(info.tiles);
  const connect = () => {
    const url = new URL(`${cfg.root}/walls/${cfg.wall}/console/stream`, location.href);
    url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
    if (cfg.token) url.searchParams.set("token", cfg.token);
    const ws = new WebSocket(url);
    let opened = false, newest = null;
    ws.onopen = () => { opened = true; };
    ws.onmessage = (event) => {  // kept; drawn when the browser next draws, if still newest
      if (newest === null) {
        requestAnimationFrame(() => {
          const text = newest;
          newest = null;
          show(groups, rows, JSON.parse(text));
        });
      }
      newest = event.data;
      api.received += 1;
      document.body.classList.remove("stale");
    };
    ws.onclose = async (event) => {
      document.body.classList.add("stale");  // what is shown is no longer known to hold
      if (event.code !== 4404) {  // gone meanwhile (a restart without it, an expiry)?
        const again = await fetch(`${cfg.root}/walls/${cfg.wall}`).catch(() => null);
        if (!again || again.status !== 404) {
          const detail = again && !again.ok ? await again.json().then((b) => b.detail,
                                                                       () => "") : "";
          summary.textContent = !again ? "the server does not answer (last state greyed): reconnecting" :
            !again.ok ? `refused (${again.status}): ${detail}; retrying every 2 s` :
            !opened ? "refused by the server (too many consoles or streams open, or it is restarting): " +
              "retrying every 2 s" :
            "disconnected; reconnecting";
          setTimeout(connect, 2000);
          return;
        }
      }
      summary.textContent = "the wall was deleted";
      api.gone = true;
    };
  };
  connect();
}

start().catch((e) => { summary.textContent = String(e); });
