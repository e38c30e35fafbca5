// wallcull's tile client: a render node in a browser (GET /walls/{wid}/view).
//
// The node stream (JSON) brings one message per frame for this page's tiles; each message is
// taken as clients/wallcull_clients/node.py takes it (lists rebuilt from the delta's base, extents
// and depth ranges kept by frame, matrices rebuilt as clients/frusta.py does), every mesh is
// fetched once, the newest frame is drawn with WebGL2 and acknowledged ({"ack": n}). A
// message that cannot be taken asks for full lists ({"full": true}). Stereo frames: the left
// eye in the left half of each tile, the right eye in the right half. With ?ids=1 each tile
// is also drawn into an R32UI target holding each leaf's draw id (leaf id + 1, 0 for the
// background), read back by window.wallcull.readIds(tile), row 0 at the top, as
// clients/wallcull_clients/render.py's Image.ids.
//
// Each tile's primary view only (both eyes in stereo), from its list, ranges and frusta: the
// message's shadows and mirrors are not drawn (no shadow maps, no mirror passes), as in the
// Python clients; a render node of its own draws those passes from their frusta and lists.
//
// A stream lost (a server restart) is opened again every 2 s; once it is, the wall and the
// scene's nodes are fetched again, and a scene that changed (its file replaced) is taken
// anew, its meshes fetched again. A full message (no base) puts every leaf back at rest
// before its own transforms move some, as a restarted server has forgotten moved leaves.

const cfg = JSON.parse(document.getElementById("wallcull-config").textContent);
const status = document.getElementById("status");
const canvas = document.getElementById("wall");
// window.wallcull: the newest frame drawn and acknowledged, full lists asked for, errors;
// readIds(tile); forget(): drop the lists held, as a node that lost its memory (for tests)
const api = window.wallcull = { drawn: -1, acked: -1, fulls: 0, errors: [], ranged: 0, readIds,
                                forget: () => node.lists.clear() };

function say(text, error = false) {  // a note in a corner, hidden while frames come
  status.textContent = text;
  status.className = error ? "error" : "";
  status.hidden = false;
  if (error) api.errors.push(text);
}

// ------------------------------------------------------------------ lists and matrices

const KEEP = 256;

function applyDelta(held, entry, base) {  // protocol.apply
  let out;
  if (base === null || entry.visible !== undefined) {
    out = Int32Array.from(entry.visible);
  } else {
    if (!held) throw new Error(`delta against frame ${base}, whose list is not held`);
    const removed = new Set(entry.removed || []), added = entry.added || [];
    const keep = held.filter((leaf) => !removed.has(leaf));
    out = new Int32Array(keep.length + added.length);
    let i = 0, j = 0, k = 0;  // merge two sorted lists, without duplicates
    while (i < keep.length || j < added.length) {
      const next = j >= added.length || (i < keep.length && keep[i] <= added[j]) ? keep[i++] : added[j++];
      if (k === 0 || out[k - 1] !== next) out[k++] = next;
    }
    out = out.subarray(0, k);
  }
  if (out.length !== entry.count) {
    throw new Error(`tile ${entry.tile}'s list does not add up: ${out.length} leaves, count ${entry.count}`);
  }
  return out;
}

function applyParts(held, entry, leaves, base) {  // protocol.apply_parts
  // leaf -> [first, count, first, count, ...]: the leaves a tile draws in part
  const out = new Map();
  if (base !== null) {
    if (!held) throw new Error(`delta against frame ${base}, whose ranges are not held`);
    const whole = new Set(entry.whole || []), listed = new Set(leaves);
    for (const [leaf, r] of held) if (!whole.has(leaf) && listed.has(leaf)) out.set(leaf, r);
  }
  for (const item of entry.ranges || []) {
    if (item.length < 3 || item.length % 2 !== 1) throw new Error(`bad ranges ${item}`);
    out.set(item[0], item.slice(1));
  }
  return out;
}

function rigid(v) {  // frusta.view: a 4x4 row-major Float64Array
  const [w, x, y, z] = v.rotation, [tx, ty, tz] = v.translation;
  return Float64Array.of(
    1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y), tx,
    2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x), ty,
    2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y), tz,
    0, 0, 0, 1);
}

function projection(extent, depth, reversed) {  // frusta.projection
  const n = depth[0], f = depth[1] === null ? Infinity : depth[1];
  const [l, r, b, t] = extent.map((e) => e * n);
  const m = new Float64Array(16);
  m[0] = 2 * n / (r - l); m[2] = (r + l) / (r - l);
  m[5] = 2 * n / (t - b); m[6] = (t + b) / (t - b);
  m[14] = -1;
  if (reversed) [m[10], m[11]] = f === Infinity ? [0, n] : [n / (f - n), f * n / (f - n)];
  else [m[10], m[11]] = f === Infinity ? [-1, -2 * n] : [-(f + n) / (f - n), -2 * f * n / (f - n)];
  return m;
}

function mul(a, b) {  // row-major 4x4 product, float64
  const out = new Float64Array(16);
  for (let r = 0; r < 4; r++) {
    for (let c = 0; c < 4; c++) {
      out[4 * r + c] = a[4 * r] * b[c] + a[4 * r + 1] * b[4 + c] + a[4 * r + 2] * b[8 + c] + a[4 * r + 3] * b[12 + c];
    }
  }
  return out;
}

class NodeState {  // clients/node.py NodeState + clients/frusta.py Frusta
  constructor() { this.reset(); }
  reset() { this.lists = new Map(); this.parts = new Map(); this.frusta = new Map(); this.frame = -1; }

  take(msg) {
    const number = msg.frame, base = msg.base ?? null;
    if (number <= this.frame) throw new Error(`frame ${number} arrived after frame ${this.frame}`);
    const held = base === null ? new Map() : this.lists.get(base);
    const heldFrusta = base === null ? new Map() : this.frusta.get(base) || new Map();
    const heldParts = base === null ? new Map() : this.parts.get(base) || new Map();
    if (!held) throw new Error(`delta against frame ${base}, which this page does not hold`);
    const lists = new Map(), parts = new Map(), now = new Map(), tiles = [];
    // a tile a delta leaves out keeps the base's list, extent and depth
    const entries = new Map([...held].map(([tile, list]) => [tile, { tile, count: list.length }]));
    for (const entry of msg.tiles) entries.set(entry.tile, entry);
    for (const tile of [...entries.keys()].sort((a, b) => a - b)) {
      const entry = entries.get(tile);
      if (base !== null && !held.has(tile) && entry.visible === undefined) {
        throw new Error(`delta for tile ${tile}, whose list of frame ${base} is not held`);
      }
      lists.set(tile, applyDelta(held.get(tile), entry, base));
      parts.set(tile, applyParts(heldParts.get(tile) || new Map(), entry, lists.get(tile), base));
      const eyes = [];
      for (const eye of ["", "left", "right"]) {
        const part = eye ? entry[eye] : entry;
        if (!part) continue;
        const shared = eye ? msg[eye]?.view : msg.view;
        const value = {};
        for (const key of ["extent", "depth"]) {
          value[key] = part[key] ?? heldFrusta.get(`${tile}/${eye}/${key}`);
          if (value[key] === undefined) {
            throw new Error(`tile ${tile}: the delta's ${key} is that of frame ${base}, which is not held`);
          }
          now.set(`${tile}/${eye}/${key}`, value[key]);
        }
        eyes.push({ eye, view: rigid(part.view ?? shared),
                    projection: projection(value.extent, value.depth, !!msg.reversed_z) });
      }
      tiles.push({ tile, leaves: lists.get(tile), ranges: parts.get(tile),
                   eyes: eyes.length > 1 ? eyes.slice(1) : eyes });
    }
    this.lists.set(number, lists);
    this.parts.set(number, parts);
    this.frusta.set(number, now);
    this.frame = number;
    for (const map of [this.lists, this.parts, this.frusta]) {  // what no delta can be based on now
      for (const k of map.keys()) if ((base !== null && k < base) || map.size > KEEP) map.delete(k);
    }
    return { number, full: base === null, reversed: !!msg.reversed_z, tiles, transforms: msg.transforms };
  }
}

// ------------------------------------------------------------------ WebGL2

const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
const clipControl = gl && gl.getExtension("EXT_clip_control");

function clipped(p, reversed) {
  // reversed-Z without EXT_clip_control: GL clips depth to [-w, w], not [0, w], so row 2
  // becomes 2 * row 2 - row 3: clip depth [0, w] maps to [-w, w] (the far plane clips again),
  // and the window depth, (z / w + 1) / 2, is the reversed matrix's z / w (GREATER, clear to 0)
  if (!reversed || clipControl) return p;
  const out = Float64Array.from(p);
  for (let c = 0; c < 4; c++) out[8 + c] = 2 * p[8 + c] - p[12 + c];
  return out;
}

const VERTEX = `#version 300 es
uniform mat4 mvp; uniform mat4 mv;
in vec3 pos; out vec3 v_eye;
void main() { vec4 p = vec4(pos, 1.0); gl_Position = mvp * p; v_eye = (mv * p).xyz; }`;
const COLOR = `#version 300 es
precision highp float;
uniform vec3 color; in vec3 v_eye; out vec4 f_color;
void main() {
  vec3 n = normalize(cross(dFdx(v_eye), dFdy(v_eye)));
  float shade = 0.25 + 0.75 * abs(dot(n, normalize(-v_eye)));
  if (!gl_FrontFacing) shade *= 0.5;
  f_color = vec4(color * shade, 1.0);
}`;
const IDS = `#version 300 es
precision highp float; precision highp int;
uniform highp uint draw_id; in vec3 v_eye; out highp uint f_id;
void main() { f_id = draw_id; }`;

function program(fragment) {
  const p = gl.createProgram();
  for (const [type, text] of [[gl.VERTEX_SHADER, VERTEX], [gl.FRAGMENT_SHADER, fragment]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, text);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(p, s);
  }
  gl.bindAttribLocation(p, 0, "pos");
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
  const u = {};
  for (const name of ["mvp", "mv", "color", "draw_id"]) u[name] = gl.getUniformLocation(p, name);
  return { p, u };
}

function drawColor(id) {  // render.draw_color: hues by the golden ratio, s 0.55, v 0.95
  const h = (id * 0.618033988749895) % 1, s = 0.55, v = 0.95, i = Math.floor(h * 6), f = h * 6 - i;
  const p = v * (1 - s), q = v * (1 - s * f), t = v * (1 - s * (1 - f));
  return [[v, t, p], [q, v, p], [p, v, t], [p, q, v], [t, p, v], [v, p, q]][i % 6];
}

// ------------------------------------------------------------------ the scene and its meshes

const headers = cfg.token ? { Authorization: `Bearer ${cfg.token}` } : {};
let scene = null;  // the wall's scene: its node table, rest and current transforms, meshes

async function getJSON(url, cache = "default") {
  const r = await fetch(url, { headers, cache });
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status} ${await r.text()}`);
  return r.json();
}

function bytes(b64) {
  const s = atob(b64), out = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
  return out.buffer;
}

function byId(nodes) {
  // GET /scenes/{name}?nodes=true's table by node id: its rows leave the clusters out (parts of
  // a leaf's triangles, never listed), so a row's id is its "id" and ids run to "count"
  const n = nodes.count ?? nodes.mesh.length, mesh = new Array(n).fill(null);
  const rest = new Float64Array(16 * n);
  nodes.mesh.forEach((k, r) => {
    const id = nodes.id ? nodes.id[r] : r;
    mesh[id] = k;
    rest.set(nodes.world[r], 16 * id);
  });
  return { mesh, rest };
}

function sceneOf(name, about, table, replaced) {
  // the scene's node table (byId) as the page holds it; meshes numbered by their sorted keys,
  // uploaded as frames need them (ready: number -> {vao, buffers, count, shift}); a scene
  // that replaced another fetches its meshes past the browser's cache (a key keeps its name
  // when the file changes, not its shape)
  const keys = [...new Set(table.mesh.filter((k) => k !== null))].sort();
  const number = new Map(keys.map((k, i) => [k, i]));
  const rest = table.rest;
  return { name, about, keys, mesh: table.mesh, rest, world: rest.slice(), ready: new Map(),
           meshOf: Int32Array.from(table.mesh, (k) => (k === null ? -1 : number.get(k))),
           cache: replaced ? "no-cache" : "default" };
}

function sameScene(s, name, about, table) {  // the scene the page holds, or was it replaced?
  return s.name === name && s.about === about && s.mesh.length === table.mesh.length &&
    table.mesh.every((k, i) => k === s.mesh[i]) && table.rest.every((v, i) => v === s.rest[i]);
}

function dropScene(s) {  // its meshes off the GPU
  for (const g of s.ready.values()) {
    gl.deleteVertexArray(g.vao);
    g.buffers.forEach((b) => gl.deleteBuffer(b));
  }
  s.ready.clear();
}

async function fetchMesh(s, m) {  // a mesh by number, as float32 about its centre (as render.py)
  // and whether its back faces are culled (single: the server says it is not double_sided, a
  // single-sided glTF mesh; a server that does not say means both faces)
  const key = s.keys[m];
  const url = `${cfg.root}/scenes/${encodeURIComponent(s.name)}/meshes/${encodeURIComponent(key)}`;
  const body = await getJSON(url, s.cache);
  const single = body.double_sided === false;
  const v = new Float32Array(bytes(body.vertices.data)), faces = new Uint32Array(bytes(body.faces.data));
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < v.length; i++) {
    lo[i % 3] = Math.min(lo[i % 3], v[i]);
    hi[i % 3] = Math.max(hi[i % 3], v[i]);
  }
  const center = v.length ? lo.map((x, k) => (x + hi[k]) / 2) : [0, 0, 0];
  for (let i = 0; i < v.length; i++) v[i] -= center[i % 3];
  return { v, faces, center, single };
}

function upload({ v, faces, center, single }) {
  const vao = gl.createVertexArray(), buffers = [gl.createBuffer(), gl.createBuffer()];
  gl.bindVertexArray(vao);
  gl.bindBuffer(gl.ARRAY_BUFFER, buffers[0]);
  gl.bufferData(gl.ARRAY_BUFFER, v, gl.STATIC_DRAW);
  gl.enableVertexAttribArray(0);
  gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, buffers[1]);
  gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, faces, gl.STATIC_DRAW);
  gl.bindVertexArray(null);
  const shift = new Float64Array(16);
  shift[0] = shift[5] = shift[10] = shift[15] = 1;
  [shift[3], shift[7], shift[11]] = center;
  return { vao, buffers, count: faces.length, shift, single };
}

function det3(m) {  // the determinant of a row-major 4x4 matrix's upper 3x3
  return m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) +
    m[2] * (m[4] * m[9] - m[5] * m[8]);
}

async function load() {
  // the wall and its scene's nodes: at the start, and again on each stream opened after one
  // was lost; a scene replaced (another file, other nodes) drops what the page held of it
  const info = await getJSON(`${cfg.root}/walls/${cfg.wall}`, "no-cache");
  const body = await getJSON(`${cfg.root}/scenes/${encodeURIComponent(info.scene)}?nodes=true`, "no-cache");
  const about = JSON.stringify([body.stats, body.bounds]), table = byId(body.nodes);
  if (!scene || !sameScene(scene, info.scene, about, table)) {
    if (scene) { dropScene(scene); pending = last = null; }
    scene = sceneOf(info.scene, about, table, scene !== null);
  }
  if (JSON.stringify(info.wall) !== JSON.stringify(wall)) {
    wall = info.wall;
    layout();
  }
}

// ------------------------------------------------------------------ layout and drawing

const tiles = new Map();  // tile -> {x, y, w, h, ids: framebuffer?}
let wall = null, last = null;

function cells() {
  // tile -> [column, row] in the canvas, row 0 on top: a grid's tiles at their own cells when
  // they fill a rectangle; else (screens, or grid tiles such as 0 and 3 of a row) side by side
  // in their order
  const side = new Map(cfg.tiles.map((t, k) => [t, [k, 0]]));
  if (!wall.cols) return side;
  const grid = cfg.tiles.map((t) => [t % wall.cols, Math.floor(t / wall.cols)]);
  const cols = grid.map((p) => p[0]), rows = grid.map((p) => p[1]);
  const c0 = Math.min(...cols), r0 = Math.min(...rows);
  const area = (Math.max(...cols) - c0 + 1) * (Math.max(...rows) - r0 + 1);
  if (area !== cfg.tiles.length) return side;
  return new Map(cfg.tiles.map((t, k) => [t, [grid[k][0] - c0, grid[k][1] - r0]]));
}

const sum = (list) => list.reduce((a, b) => a + b, 0);

function spans(place, size) {  // the columns' widths and the rows' heights: their largest tile's
  const cols = [], rows = [];
  for (const [t, [c, r]] of place) {
    const [w, h] = size(t);
    cols[c] = Math.max(cols[c] || 0, w);
    rows[r] = Math.max(rows[r] || 0, h);
  }
  return [cols, rows];
}

function idTarget(w, h) {  // an R32UI target and its depth, for ?ids=1
  const fbo = gl.createFramebuffer(), rbs = [gl.createRenderbuffer(), gl.createRenderbuffer()];
  gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
  const parts = [[rbs[0], gl.R32UI, gl.COLOR_ATTACHMENT0], [rbs[1], gl.DEPTH_COMPONENT24, gl.DEPTH_ATTACHMENT]];
  for (const [rb, format, at] of parts) {
    gl.bindRenderbuffer(gl.RENDERBUFFER, rb);
    gl.renderbufferStorage(gl.RENDERBUFFER, format, w, h);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, at, gl.RENDERBUFFER, rb);
  }
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  return { fbo, rbs };
}

function layout() {
  // each tile at its own resolution (a screen's, or the grid's), all scaled by one factor: as
  // large as the window holds, each tile's aspect kept; ?size= fixes every tile's pixels
  const place = cells(), dpr = window.devicePixelRatio || 1;
  const res = (t) => cfg.size || (wall.screens ? wall.screens[t].resolution : wall.resolution);
  let scale = 1;
  if (!cfg.size) {
    const [cols, rows] = spans(place, res);
    scale = Math.min(window.innerWidth * dpr / sum(cols), window.innerHeight * dpr / sum(rows));
  }
  const size = (t) => res(t).map((v) => Math.max(1, Math.floor(v * scale)));
  const [cols, rows] = spans(place, size);
  canvas.width = sum(cols);
  canvas.height = sum(rows);
  canvas.style.width = `${canvas.width / (cfg.size ? 1 : dpr)}px`;
  for (const [t, [c, r]] of place) {
    const old = tiles.get(t), [w, h] = size(t);
    if (old && old.ids) { gl.deleteFramebuffer(old.ids.fbo); old.ids.rbs.forEach((b) => gl.deleteRenderbuffer(b)); }
    // GL's rows count from the bottom: a tile at the top left of its cell
    const y = canvas.height - sum(rows.slice(0, r)) - h;
    tiles.set(t, { x: sum(cols.slice(0, c)), y, w, h, ids: cfg.ids ? idTarget(w, h) : null });
  }
}

function drawTile(prog, frame, entry, x, y, w, h) {
  const reversed = frame.reversed, s = frame.scene;
  if (clipControl) {  // reversed-Z: clip depth in [0, 1], as render.py's glClipControl
    const c = clipControl;
    c.clipControlEXT(c.LOWER_LEFT_EXT, reversed ? c.ZERO_TO_ONE_EXT : c.NEGATIVE_ONE_TO_ONE_EXT);
  }
  gl.depthFunc(reversed ? gl.GREATER : gl.LESS);
  gl.useProgram(prog.p);
  const eyes = entry.eyes, ew = Math.floor(w / eyes.length);
  eyes.forEach((eye, k) => {
    gl.viewport(x + k * ew, y, eyes.length > 1 && k === 1 ? w - ew : ew, h);
    const projection = clipped(eye.projection, reversed);
    for (const leaf of entry.leaves) {
      const m = s.meshOf[leaf];
      if (m < 0) continue;
      const g = s.ready.get(m);
      if (!g.count) continue;
      const mv = mul(eye.view, mul(s.world.subarray(16 * leaf, 16 * leaf + 16), g.shift));
      if (g.single) {  // back faces culled; its front winds clockwise where its placement mirrors
        gl.enable(gl.CULL_FACE);
        gl.cullFace(gl.BACK);
        gl.frontFace(det3(mv) < 0 ? gl.CW : gl.CCW);
      } else {
        gl.disable(gl.CULL_FACE);
      }
      gl.uniformMatrix4fv(prog.u.mvp, true, Float32Array.from(mul(projection, mv)));
      if (prog.u.mv) gl.uniformMatrix4fv(prog.u.mv, true, Float32Array.from(mv));
      if (prog.u.color) gl.uniform3fv(prog.u.color, drawColor(leaf + 1));
      if (prog.u.draw_id) gl.uniform1ui(prog.u.draw_id, leaf + 1);
      gl.bindVertexArray(g.vao);
      const r = entry.ranges.get(leaf);
      if (r === undefined) {
        gl.drawElements(gl.TRIANGLES, g.count, gl.UNSIGNED_INT, 0);
      } else {  // a leaf drawn in part: one call a range of triangles (12 bytes each)
        for (let k = 0; k < r.length; k += 2) gl.drawElements(gl.TRIANGLES, 3 * r[k + 1], gl.UNSIGNED_INT, 12 * r[k]);
      }
    }
  });
}

function draw(frame) {
  gl.enable(gl.DEPTH_TEST);
  gl.enable(gl.SCISSOR_TEST);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.scissor(0, 0, canvas.width, canvas.height);
  gl.clearColor(0, 0, 0, 1);
  gl.clear(gl.COLOR_BUFFER_BIT);
  api.ranged = 0;  // leaves the frame draws in part, by their ranges
  for (const entry of frame.tiles) {
    if (tiles.has(entry.tile)) api.ranged += entry.ranges.size;
    const t = tiles.get(entry.tile);
    if (!t) continue;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.scissor(t.x, t.y, t.w, t.h);
    gl.clearColor(0.1, 0.1, 0.1, 1);
    gl.clearDepth(frame.reversed ? 0 : 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    drawTile(programs.color, frame, entry, t.x, t.y, t.w, t.h);
    if (t.ids) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, t.ids.fbo);
      gl.scissor(0, 0, t.w, t.h);
      gl.clearBufferuiv(gl.COLOR, 0, Uint32Array.of(0, 0, 0, 0));
      gl.clearBufferfv(gl.DEPTH, 0, Float32Array.of(frame.reversed ? 0 : 1));
      drawTile(programs.ids, frame, entry, 0, 0, t.w, t.h);
    }
  }
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.bindVertexArray(null);
  gl.disable(gl.CULL_FACE);
}

function readIds(tile, base64 = false) {
  // the id target of a tile (?ids=1): {width, height, ids}, row 0 on top; ids an Array, or
  // with base64 the little-endian uint32 bytes in base64 (a quicker way out of the page)
  const t = tiles.get(tile);
  if (!t || !t.ids) throw new Error(`tile ${tile} has no id target (open the page with ?ids=1)`);
  const px = new Uint32Array(t.w * t.h * 4), ids = new Uint32Array(t.w * t.h);
  gl.bindFramebuffer(gl.FRAMEBUFFER, t.ids.fbo);
  gl.readPixels(0, 0, t.w, t.h, gl.RGBA_INTEGER, gl.UNSIGNED_INT, px);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  for (let r = 0; r < t.h; r++) {
    for (let c = 0; c < t.w; c++) ids[r * t.w + c] = px[4 * ((t.h - 1 - r) * t.w + c)];
  }
  if (!base64) return { width: t.w, height: t.h, ids: Array.from(ids) };
  const b = new Uint8Array(ids.buffer);
  let text = "";
  for (let i = 0; i < b.length; i += 0x8000) text += String.fromCharCode(...b.subarray(i, i + 0x8000));
  return { width: t.w, height: t.h, ids: btoa(text) };
}

// ------------------------------------------------------------------ the stream

const node = new NodeState();
let socket = null, pending = null, drawing = false, programs = null, lost = false;

function strayLeaf(frame) {  // a leaf listed or moved that the scene the page holds lacks
  const n = frame.scene.meshOf.length;
  for (const e of frame.tiles) for (const leaf of e.leaves) if (leaf >= n) return leaf;
  return (frame.transforms?.ids || []).find((leaf) => leaf >= n);
}

function moveLeaves(frame) {
  // a full message puts every leaf back at rest, then moves those it carries (every moved leaf
  // of its lists, protocol.transforms), as node.py's reset; a delta moves those it names
  const s = frame.scene, moved = frame.transforms;
  if (frame.full) s.world.set(s.rest);
  if (moved) moved.ids.forEach((leaf, k) => s.world.set(moved.matrices[k], 16 * leaf));
}

async function drawPending() {
  while (pending) {
    const frame = pending, s = frame.scene;
    pending = null;
    const needed = new Set();
    for (const e of frame.tiles) {
      for (const leaf of e.leaves) if (s.meshOf[leaf] >= 0) needed.add(s.meshOf[leaf]);
    }
    for (const m of needed) {
      if (s.ready.has(m)) continue;
      const body = await fetchMesh(s, m);
      if (s !== scene) break;  // the scene was replaced meanwhile
      s.ready.set(m, upload(body));
    }
    if (s !== scene || (pending && pending.number > frame.number)) continue;  // a newer frame came meanwhile
    draw(frame);
    last = frame;
    api.drawn = frame.number;
    if (socket && socket.readyState === WebSocket.OPEN) {
      socket.send(JSON.stringify({ ack: frame.number }));
      api.acked = frame.number;
    }
    status.hidden = true;
  }
  drawing = false;
}

function schedule() {
  if (drawing) return;
  drawing = true;
  const run = () => drawPending().catch((e) => { drawing = false; say(String(e), true); });
  if (document.hidden) setTimeout(run, 0); else requestAnimationFrame(run);
}

function take(data) {  // a message of the stream, read against the scene the page holds
  const msg = JSON.parse(data);
  if (msg.error) { say(`server: ${msg.error}`, true); return; }
  try {
    const frame = node.take(msg);
    frame.scene = scene;
    const stray = strayLeaf(frame);
    if (stray !== undefined) {  // not the scene the server culls: fetched again on a new stream
      say(`frame ${frame.number} has leaf ${stray}, which scene ${scene.name} as this page holds it ` +
          `(${scene.meshOf.length} nodes) lacks: the scene changed; fetching it again`, true);
      socket.close(RELOAD, "the scene changed");
      return;
    }
    moveLeaves(frame);
    pending = frame;
    schedule();
  } catch (e) {  // a delta this page cannot apply: start again from full lists
    node.reset();
    api.fulls += 1;
    say(`${e.message}: asking for full lists`, true);
    socket.send(JSON.stringify({ full: true }));
  }
}

// Why the server refused this page's stream: a browser is not shown a refused handshake's
// answer, so the page asks the wall, then the packets route of its first tile, which takes the
// same credential. A refusal retrying cannot mend (401, 403, 404, 422) is said, and the page
// stops; else (429, a wall waiting for its scene: 503, a restart) it tries again.
const FINAL = new Set([401, 403, 404, 422]);
// Closes of an open stream that a server restart brings (1001 going away, 1006 lost, 1012
// restarting), and the page's own when its scene changed: a plain note, tried again
const RELOAD = 4000, ROUTINE = new Set([1001, 1006, 1012, RELOAD]);
const RETRY = 2000;

async function refusal() {  // {status, detail}, null when the server says nothing; throws if it does not answer
  const wallAnswer = await fetch(`${cfg.root}/walls/${cfg.wall}`);
  if (!wallAnswer.ok) return { status: wallAnswer.status, detail: (await wallAnswer.json()).detail };
  if (!cfg.tiles.length) return { status: 422, detail: "this page has no tiles: ?tiles=0-3, or a node's ?token=" };
  const r = await fetch(`${cfg.root}/walls/${cfg.wall}/tiles/${cfg.tiles[0]}/packets/latest?wait=0`, { headers });
  if (r.status === 401 || r.status === 403) return { status: r.status, detail: (await r.json()).detail };
  return null;
}

async function closed(event, opened) {  // say why a stream closed; whether to try again
  const text = `stream closed (${event.code}${event.reason ? ": " + event.reason : ""})`;
  if (event.code === 4404) { say(text, true); return false; }  // the wall was deleted
  if (opened) {
    if (ROUTINE.has(event.code)) say("reconnecting…"); else say(text, true);
    return true;
  }
  let why;  // refused at the handshake: why, and whether to try again
  try {
    why = await refusal();
  } catch {
    say("reconnecting…: the server does not answer");
    return true;
  }
  if (!why) {
    say(`refused by the server (too many streams on these tiles, or it is restarting): retrying every ${RETRY / 1000} s`, true);
    return true;
  }
  say(`refused (${why.status}): ${why.detail}`, true);
  if (FINAL.has(why.status)) api.refused = why.status;
  return !FINAL.has(why.status);
}

function connect() {
  const url = new URL(`${cfg.root}/walls/${cfg.wall}/nodes/stream`, location.href);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  url.searchParams.set("format", "json");
  url.searchParams.set("tiles", cfg.spec);
  if (cfg.token) url.searchParams.set("token", cfg.token);
  node.reset();
  let opened = false, loaded = Promise.resolve(true);
  socket = new WebSocket(url);
  socket.onopen = () => {  // a note left by a lost stream goes; the first frame's is said
    opened = true;
    if (last) status.hidden = true; else say("connected: waiting for frames");
    if (!lost) return;
    const ws = socket;  // after a lost stream, the wall and scene again: messages wait for them
    loaded = load().then(() => { lost = false; return true; },
                         (e) => { say(String(e), true); ws.close(RELOAD, "the scene could not be fetched"); return false; });
  };
  socket.onmessage = (event) => { loaded.then((ok) => ok && take(event.data)); };
  socket.onclose = async (event) => {
    lost = true;
    if (await closed(event, opened)) setTimeout(connect, RETRY);
  };
}

async function start() {
  if (!gl) { say("this browser has no WebGL2", true); return; }
  programs = { color: program(COLOR), ids: program(IDS) };
  await load();
  window.addEventListener("resize", () => { if (!cfg.size) { layout(); if (last) draw(last); } });
  connect();
}

start().catch((e) => say(String(e), true));
