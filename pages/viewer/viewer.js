// The capture page's 3D view: the fitted mesh (glTF) to turn, zoom and light, in its own
// colours, plain, or coloured by its accuracy against the scan; the fused cloud and the
// keyframe cameras on demand; the scan the run was scored against beside it (the view split
// in two, one camera: the reconstruction left, the scan right). Reads the page's JSON (id
// "facecap-data"); THREE is the vendored three.js bundle. Sets window.facecap = {ready,
// reason, mode, setMode, toggle, measure, measurement, showPreset, vertexOnScreen, setLight,
// setScan, split, views, drawn, still}: ready once the mesh is shown, reason when it cannot
// be; views is how many views the last frame drew; drawn counts the frames drawn, still the
// frames since the last one (the view has settled when it grows). Measure: two clicks on the
// mesh (each snapped to the nearest vertex of the triangle hit) give their distance straight
// and along the surface (the path of facecap_core/measure.py: a Steiner-point graph searched
// by A*, then straightened along its edges), ± the metric scale's 1σ; the presets measure
// between two landmarks and say the report's anatomical figure first. A textured mesh.glb
// is split at its UV seams: the mesh's own vertices first, then copies of seam vertices (its
// userData: template_vertices, seam_vertex); what is indexed by mesh vertex (the heat map,
// the measured vertices) is spread onto the copies, and a copy clicked is its mesh vertex.
(function () {
  "use strict";
  const data = JSON.parse(document.getElementById("facecap-data").textContent);
  const bytes = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const canvas = document.getElementById("canvas");
  const renderer = new THREE.WebGLRenderer({canvas, antialias: true, preserveDrawingBuffer: true});
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf4f4f4);
  const camera = new THREE.PerspectiveCamera(30, 1, 1, 1e5);
  scene.add(camera);
  const sky = new THREE.HemisphereLight(0xffffff, 0x606060, 1.6);
  scene.add(sky);
  const headlight = new THREE.DirectionalLight(0xffffff, 1.8);
  // Follows the viewer: it shines along the line of sight (the side facing the viewer is
  // lit); the Light slider turns it round to the side, in the camera's own frame.
  headlight.position.set(0, 0, 1);
  camera.add(headlight);
  headlight.target = camera;
  const controls = new THREE.OrbitControls(camera, canvas);
  controls.enableDamping = true;
  const state = {ready: false, mode: "colour", setMode, toggle, measure: measureVertices,
                 measurement: null, measuring: false, vertexOnScreen, setLight, setScan,
                 split: false, views: 0, drawn: 0, still: 0};
  window.facecap = state;
  // Drawn when something changed (a turn, a zoom, a mode, a size), not every frame: an open
  // page idles rather than keeping a core (or a laptop's GPU) busy.
  let stale = true;
  controls.addEventListener("change", () => { stale = true; });

  // The width of one view: the canvas's, or half of it when the scan is beside the mesh.
  const viewWidth = () => (state.split ? canvas.clientWidth / 2 : canvas.clientWidth);
  function resize() {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * renderer.getPixelRatio()) ||
        canvas.height !== Math.round(h * renderer.getPixelRatio())) {
      renderer.setSize(w, h, false);
      stale = true;
    }
    const aspect = viewWidth() / Math.max(h, 1);
    if (camera.aspect !== aspect) {
      camera.aspect = aspect;
      camera.updateProjectionMatrix();
      stale = true;
    }
  }
  // A point of the (left) view, in pixels, and back: the clicks and the tests' aims.
  const toScreen = (p) => [(p.x + 1) / 2 * viewWidth(), (1 - p.y) / 2 * canvas.clientHeight];
  const toNdc = (x, y) => new THREE.Vector2(x / viewWidth() * 2 - 1,
                                            1 - y / canvas.clientHeight * 2);

  function buffer(b64, Type) {
    const raw = bytes(b64);
    return new Type(raw.buffer, raw.byteOffset, raw.byteLength / Type.BYTES_PER_ELEMENT);
  }

  let mesh = null, colours = null;
  // The mesh vertex of each glTF vertex (the identity but for seam copies), and how many
  // mesh vertices there are: the heat map and the measured vertices count in those.
  let meshVertex = null, meshVertices = 0;
  // Both sides drawn: the fitted mesh is open (the neck, behind the ears), and its inside,
  // seen through an opening or from behind, is part of what a user turns to look at.
  const materials = {
    // Replaced by the glTF's own material when that has a texture (the fitting stage's atlas).
    colour: new THREE.MeshStandardMaterial({vertexColors: true, roughness: 0.8,
                                            side: THREE.DoubleSide}),
    plain: new THREE.MeshStandardMaterial({color: 0xb8b8b8, roughness: 0.7,  // grey: the shape
                                           side: THREE.DoubleSide}),
    accuracy: new THREE.MeshStandardMaterial({vertexColors: true, roughness: 0.9,
                                              side: THREE.DoubleSide}),
  };
  const extras = {};

  function setMode(mode) {
    if (!mesh || !(mode in materials) || (mode === "accuracy" && !data.accuracy)) return false;
    const attribute = mode === "accuracy" ? "heat" : "original";
    if (materials[mode].vertexColors) mesh.geometry.setAttribute("color", colours[attribute]);
    mesh.material = materials[mode];
    document.getElementById("colourbar").hidden = mode !== "accuracy";
    for (const button of document.querySelectorAll("[data-mode]"))
      button.setAttribute("aria-pressed", String(button.dataset.mode === mode));
    state.mode = mode;
    stale = true;
    return true;
  }

  // A click (not a drag) near a camera, while the cameras are shown, opens what it saw.
  const centres = data.cameras ? buffer(data.cameras.centres, Float32Array) : null;
  function cameraOnScreen(i) {
    const p = new THREE.Vector3(centres[3 * i], centres[3 * i + 1], centres[3 * i + 2]);
    p.project(camera);
    if (p.z > 1) return null;  // behind the viewer
    return toScreen(p);
  }
  function showKeyframe(i) {
    const figure = document.getElementById("keyframe");
    const image = data.cameras.images[i];
    if (!image) return false;
    figure.querySelector("img").src = image;
    figure.querySelector("figcaption").textContent =
      `keyframe ${i + 1} of ${data.cameras.count} (frame ${data.cameras.frames[i]})`;
    figure.hidden = false;
    state.shown = i;
    return true;
  }
  state.cameraOnScreen = cameraOnScreen;
  let pressed = null;
  canvas.addEventListener("pointerdown", (e) => { pressed = [e.offsetX, e.offsetY]; });
  canvas.addEventListener("pointerup", (e) => {
    if (state.measuring) return;  // a click picks a point to measure (below)
    if (!pressed || !extras.cameras || !extras.cameras.visible) return;
    if (Math.hypot(e.offsetX - pressed[0], e.offsetY - pressed[1]) > 4) return;  // a drag
    let best = -1, nearest = 24;  // px
    for (let i = 0; i < data.cameras.count; i++) {
      const at = cameraOnScreen(i);
      if (!at) continue;
      const d = Math.hypot(at[0] - e.offsetX, at[1] - e.offsetY);
      if (d < nearest) { nearest = d; best = i; }
    }
    if (best >= 0) showKeyframe(best);
  });
  document.getElementById("keyframe").addEventListener("click", (e) => {
    e.currentTarget.hidden = true;
  });

  const stepBack = {distance: null};  // the view's distance before the cameras were shown
  function toggle(name) {
    if (!(name in extras)) return false;
    extras[name].visible = !extras[name].visible;
    if (name === "cameras") {
      // Step back far enough to see the cameras around the head, and forwards again to
      // where the view was when they are hidden (whichever way it was turned meanwhile).
      const offset = camera.position.clone().sub(controls.target);
      if (extras.cameras.visible) {
        stepBack.distance = offset.length();
        offset.setLength(Math.max(offset.length(), 1.8 * data.cameras.distance));
      } else if (stepBack.distance !== null) {
        offset.setLength(stepBack.distance);
        stepBack.distance = null;
      }
      camera.position.copy(controls.target).add(offset);
    }
    document.querySelector(`[data-toggle="${name}"]`)
      .setAttribute("aria-pressed", String(extras[name].visible));
    stale = true;
    return extras[name].visible;
  }

  // -- Measure ------------------------------------------------------------------------------
  // Vertex v is node v; point k (of STEINER) inside edge e is node V + e * STEINER + k, at
  // (k + 1) / (STEINER + 1) of the way from the edge's lower vertex id: as measure.py.
  const STEINER = 3, SWEEPS = 400, GOLDEN_STEPS = 30, GOLDEN = (Math.sqrt(5) - 1) / 2;
  let topology = null;
  function buildTopology() {
    // Over the mesh's own vertices: a seam copy's triangles join its mesh vertex's, so that
    // a path crosses the seams.
    const geometry = mesh.geometry, V = meshVertices;
    const position = geometry.getAttribute("position").array.subarray(0, 3 * V);
    const drawn = geometry.index ? geometry.index.array
      : Uint32Array.from({length: meshVertex.length}, (_, i) => i);
    const index = Uint32Array.from(drawn, (i) => meshVertex[i]);
    const F = index.length / 3;
    const edgeOf = new Map(), edges = [], edgeFaceList = [];
    const faceEdges = new Int32Array(3 * F);
    for (let f = 0; f < F; f++) {
      for (let k = 0; k < 3; k++) {
        const a = index[3 * f + k], b = index[3 * f + (k + 1) % 3];
        const lo = Math.min(a, b), hi = Math.max(a, b), key = lo * V + hi;
        let e = edgeOf.get(key);
        if (e === undefined) {
          e = edges.length / 2;
          edgeOf.set(key, e);
          edges.push(lo, hi);
          edgeFaceList.push(f, -1);
        } else edgeFaceList[2 * e + 1] = f;
        faceEdges[3 * f + k] = e;
      }
    }
    const start = new Int32Array(V + 1);  // the faces round each vertex, as a CSR list
    for (let i = 0; i < index.length; i++) start[index[i] + 1]++;
    for (let v = 0; v < V; v++) start[v + 1] += start[v];
    const fill = start.slice(0, V), vertexFaces = new Int32Array(index.length);
    for (let i = 0; i < index.length; i++) vertexFaces[fill[index[i]]++] = (i / 3) | 0;
    topology = {position, index, V, F, edges: Int32Array.from(edges),
                edgeFaces: Int32Array.from(edgeFaceList), faceEdges, start, vertexFaces,
                nodes: V + edges.length / 2 * STEINER};
    return topology;
  }

  function nodePoint(n, out) {
    const {position, V, edges} = topology;
    if (n < V) {
      out[0] = position[3 * n]; out[1] = position[3 * n + 1]; out[2] = position[3 * n + 2];
      return out;
    }
    const e = Math.floor((n - V) / STEINER), t = ((n - V) % STEINER + 1) / (STEINER + 1);
    const u = edges[2 * e], v = edges[2 * e + 1];
    for (let c = 0; c < 3; c++)
      out[c] = position[3 * u + c] + t * (position[3 * v + c] - position[3 * u + c]);
    return out;
  }
  const dist3 = (p, q) => Math.hypot(p[0] - q[0], p[1] - q[1], p[2] - q[2]);

  function surfacePath(a, b) {
    // A* over the Steiner graph (the straight distance to b is never more than what is
    // left), through no vertex but its ends, then straightened: measure.py's path.
    const topo = topology || buildTopology();
    const {V, index, faceEdges, edgeFaces, start, vertexFaces} = topo;
    if (a === b) return {length: 0, points: [nodePoint(a, [0, 0, 0])]};
    const g = new Float64Array(topo.nodes).fill(Infinity);
    const before = new Int32Array(topo.nodes).fill(-1);
    const closed = new Uint8Array(topo.nodes);
    const target = nodePoint(b, [0, 0, 0]), p = [0, 0, 0], q = [0, 0, 0];
    const keys = [], values = [];  // a binary heap of (estimate, node)
    const push = (key, value) => {
      let i = keys.length;
      keys.push(key); values.push(value);
      while (i > 0) {
        const up = (i - 1) >> 1;
        if (keys[up] <= key) break;
        keys[i] = keys[up]; values[i] = values[up]; i = up;
      }
      keys[i] = key; values[i] = value;
    };
    const pop = () => {
      const top = values[0], lastKey = keys.pop(), lastValue = values.pop();
      if (keys.length) {
        let i = 0;
        for (;;) {
          let child = 2 * i + 1;
          if (child >= keys.length) break;
          if (child + 1 < keys.length && keys[child + 1] < keys[child]) child++;
          if (keys[child] >= lastKey) break;
          keys[i] = keys[child]; values[i] = values[child]; i = child;
        }
        keys[i] = lastKey; values[i] = lastValue;
      }
      return top;
    };
    g[a] = 0;
    push(dist3(nodePoint(a, p), target), a);
    const faceNodes = new Int32Array(3 + 3 * STEINER);
    while (keys.length) {
      const n = pop();
      if (closed[n]) continue;
      closed[n] = 1;
      if (n === b) break;
      nodePoint(n, p);
      let faces;
      if (n < V) faces = vertexFaces.subarray(start[n], start[n + 1]);
      else {
        const e = Math.floor((n - V) / STEINER);
        faces = edgeFaces[2 * e + 1] < 0 ? [edgeFaces[2 * e]] : [edgeFaces[2 * e], edgeFaces[2 * e + 1]];
      }
      for (const f of faces) {
        for (let k = 0; k < 3; k++) {
          faceNodes[k] = index[3 * f + k];
          for (let s = 0; s < STEINER; s++)
            faceNodes[3 + k * STEINER + s] = V + faceEdges[3 * f + k] * STEINER + s;
        }
        for (const m of faceNodes) {
          if (m === n || closed[m] || (m < V && m !== b)) continue;
          const d = g[n] + dist3(p, nodePoint(m, q));
          if (d < g[m]) {
            g[m] = d;
            before[m] = n;
            push(d + dist3(q, target), m);
          }
        }
      }
    }
    if (!closed[b]) return {length: Infinity, points: []};
    const chain = [b];
    while (chain[chain.length - 1] !== a) chain.push(before[chain[chain.length - 1]]);
    const points = straighten(chain.reverse());
    let length = 0;
    for (let i = 1; i < points.length; i++) length += dist3(points[i - 1], points[i]);
    return {length, points};
  }

  function straighten(nodes) {
    // Each point inside an edge slides along it to where the path is shortest, odd points
    // then even ones, by golden section with its neighbours held; vertices stay.
    const {position, V, edges} = topology, n = nodes.length;
    const from = new Float64Array(3 * n), step = new Float64Array(3 * n);
    const t = new Float64Array(n), inner = new Uint8Array(n);
    for (let i = 0; i < n; i++) {
      const node = nodes[i];
      let u = node, v = node;
      if (node >= V) {
        const e = Math.floor((node - V) / STEINER);
        u = edges[2 * e]; v = edges[2 * e + 1];
        t[i] = ((node - V) % STEINER + 1) / (STEINER + 1);
        inner[i] = 1;
      }
      for (let c = 0; c < 3; c++) {
        from[3 * i + c] = position[3 * u + c];
        step[3 * i + c] = position[3 * v + c] - position[3 * u + c];
      }
    }
    const at = (i, x) => [from[3 * i] + x * step[3 * i], from[3 * i + 1] + x * step[3 * i + 1],
                          from[3 * i + 2] + x * step[3 * i + 2]];
    const total = () => {
      let sum = 0;
      for (let i = 1; i < n; i++) sum += dist3(at(i - 1, t[i - 1]), at(i, t[i]));
      return sum;
    };
    let length = Infinity;
    for (let sweep = 0; sweep < SWEEPS; sweep++) {
      for (const first of [1, 2]) {
        for (let i = first; i < n - 1; i += 2) {
          if (!inner[i]) continue;
          const prev = at(i - 1, t[i - 1]), next = at(i + 1, t[i + 1]);
          const cost = (x) => { const r = at(i, x); return dist3(r, prev) + dist3(r, next); };
          let lo = 0, hi = 1;
          for (let k = 0; k < GOLDEN_STEPS; k++) {
            const d = GOLDEN * (hi - lo), x1 = hi - d, x2 = lo + d;
            if (cost(x1) < cost(x2)) hi = x2; else lo = x1;
          }
          t[i] = (lo + hi) / 2;
        }
      }
      const shorter = total();
      if (shorter > length * (1 - 1e-7)) break;
      length = shorter;
    }
    return Array.from({length: n}, (_, i) => at(i, t[i]));
  }

  function vertexOnScreen(i) {
    const position = mesh.geometry.getAttribute("position");
    const p = new THREE.Vector3().fromBufferAttribute(position, i).project(camera);
    if (p.z > 1) return null;
    return toScreen(p);
  }

  const sigmaPct = data.measure ? data.measure.sigma_pct : null;
  function distanceText(mm) {
    if (!Number.isFinite(mm)) return "–";
    if (sigmaPct === null || sigmaPct === undefined)
      return `${mm.toFixed(1)} mm (the metric scale's uncertainty is not known)`;
    return `${mm.toFixed(1)} mm ± ${(mm * sigmaPct / 100).toFixed(1)} mm ` +
      `(±${sigmaPct.toFixed(1)} %, 1σ)`;
  }

  const marks = new THREE.Group();
  marks.renderOrder = 10;
  scene.add(marks);
  function drawMeasure(points, ends) {
    for (const child of [...marks.children]) {
      marks.remove(child);
      child.geometry.dispose();
    }
    const radius = mesh.geometry.boundingSphere.radius;
    const over = {depthTest: false, transparent: true};
    for (const e of ends) {
      const dot = new THREE.Mesh(new THREE.SphereGeometry(radius * 0.012, 12, 8),
                                 new THREE.MeshBasicMaterial({color: 0xe03020, ...over}));
      dot.position.set(...e);
      dot.renderOrder = 11;
      marks.add(dot);
    }
    if (ends.length === 2) {
      const straight = new THREE.Line(new THREE.BufferGeometry().setFromPoints(
        ends.map((e) => new THREE.Vector3(...e))),
        new THREE.LineBasicMaterial({color: 0xe03020, ...over}));
      const along = new THREE.Line(new THREE.BufferGeometry().setFromPoints(
        points.map((e) => new THREE.Vector3(...e))),
        new THREE.LineBasicMaterial({color: 0x1050d0, ...over}));
      straight.renderOrder = along.renderOrder = 10;
      marks.add(straight, along);
    }
    stale = true;
  }

  function measureVertices(a, b, name, shown) {
    // The distance from vertex a to b: drawn (red straight, blue along the surface) and
    // said; ``shown`` (a preset's figures from report.json) is said instead of this page's.
    if (!topology) buildTopology();
    const ends = [nodePoint(a, [0, 0, 0]), nodePoint(b, [0, 0, 0])];
    const path = surfacePath(a, b);
    const straight = dist3(ends[0], ends[1]);
    const surface = Math.max(path.length, straight);
    state.measurement = {a, b, name: name || null, straight, surface, shown: shown || null};
    drawMeasure(path.points, ends);
    const s = shown && Number.isFinite(shown.straight) ? shown.straight : straight;
    const r = shown && Number.isFinite(shown.surface) ? shown.surface : surface;
    // A preset also says its anatomical figure: the distance less where the fit puts the
    // landmark vertices, ± the scale's and that placement's 1σ (report.json's).
    const anat = shown && shown.anatomical;
    let said = "";
    if (anat && Number.isFinite(anat.mm))
      said = (Number.isFinite(anat.sigma_mm) ?
        `${anat.mm.toFixed(1)} mm ± ${anat.sigma_mm.toFixed(1)} mm (1σ, with where the ` +
        "landmarks sit)" : `${anat.mm.toFixed(1)} mm (its uncertainty is not known)`) +
        "; between its landmark vertices: ";
    document.getElementById("measure-result").textContent =
      `${name ? name + ": " : ""}${said}straight ${distanceText(s)}; along the surface ` +
      `${distanceText(r)}`;
    return state.measurement;
  }

  function setMeasuring(on) {
    state.measuring = on;
    document.getElementById("measure").hidden = !on;
    document.getElementById("measure-button").setAttribute("aria-pressed", String(on));
    marks.visible = on;
    picked.length = 0;
    stale = true;
  }

  function showPreset(key) {
    const preset = data.measure.presets.find((p) => p.key === key);
    if (!preset) return null;
    if (!preset.vertices.every((v) => Number.isInteger(v) && v >= 0 && v < meshVertices))
      return null;
    if (!state.measuring) setMeasuring(true);
    const mm = (d) => (d && typeof d.mm === "number" ? d.mm : NaN);
    return measureVertices(preset.vertices[0], preset.vertices[1], preset.name,
                           {straight: mm(preset.straight), surface: mm(preset.surface),
                            anatomical: preset.anatomical || null});
  }
  state.showPreset = showPreset;

  const picked = [];
  const raycaster = new THREE.Raycaster();
  canvas.addEventListener("pointerup", (e) => {
    if (!state.measuring || !pressed || !mesh.visible) return;
    if (Math.hypot(e.offsetX - pressed[0], e.offsetY - pressed[1]) > 4) return;  // a drag
    raycaster.setFromCamera(toNdc(e.offsetX, e.offsetY), camera);
    const hit = raycaster.intersectObject(mesh, false)[0];
    if (!hit) return;
    const position = mesh.geometry.getAttribute("position"), v = new THREE.Vector3();
    let best = hit.face.a, nearest = Infinity;
    for (const i of [hit.face.a, hit.face.b, hit.face.c]) {
      const d = v.fromBufferAttribute(position, i).distanceTo(hit.point);
      if (d < nearest) { nearest = d; best = i; }
    }
    best = meshVertex[best];  // a seam copy is its mesh vertex
    if (picked.length === 2) picked.length = 0;
    picked.push(best);
    state.picked = [...picked];
    if (!topology) buildTopology();
    if (picked.length === 1) {
      drawMeasure([], [nodePoint(best, [0, 0, 0])]);
      document.getElementById("measure-result").textContent = "Click a second point.";
    } else measureVertices(picked[0], picked[1]);
  });

  function setLight(degrees) {
    // The light from the viewer's side (0) round to the left or right (±90: raking, across
    // the face, so that every bump casts its shading); the sky light dims as it turns.
    const r = THREE.MathUtils.degToRad(degrees);
    headlight.position.set(Math.sin(r), 0.15, Math.cos(r));
    sky.intensity = 1.6 * (0.35 + 0.65 * Math.cos(r));
    state.light = degrees;
    stale = true;
  }

  // -- The scan beside the mesh ----------------------------------------------------------------
  let scanMesh = null;
  const splitBack = {distance: null};  // the view's distance before the view was split
  function setScan(on) {
    if (!data.scan || !mesh) return false;
    if (!scanMesh) addScan();  // made when first asked for: the page is ready no later
    state.split = Boolean(on);
    document.getElementById("scan-button").setAttribute("aria-pressed", String(state.split));
    document.getElementById("scan-labels").hidden = !state.split;
    resize();
    // A half as wide sees less across: step back until the face fits its width, and
    // forwards again when the view is whole.
    const offset = camera.position.clone().sub(controls.target);
    if (state.split) {
      const fits = mesh.geometry.boundingSphere.radius * 1.1 /
        (camera.aspect * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
      if (offset.length() < fits) {
        splitBack.distance = offset.length();
        offset.setLength(fits);
      }
    } else if (splitBack.distance !== null) {
      offset.setLength(splitBack.distance);
      splitBack.distance = null;
    }
    camera.position.copy(controls.target).add(offset);
    stale = true;
    return state.split;
  }
  function addScan() {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(buffer(data.scan.positions, Float32Array), 3));
    geometry.setIndex(new THREE.BufferAttribute(buffer(data.scan.index, Uint32Array), 1));
    geometry.computeVertexNormals();
    // Grey, as Plain: the two shapes compared under the same light.
    scanMesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial(
      {color: 0xb8b8b8, roughness: 0.7, side: THREE.DoubleSide}));
    scanMesh.visible = false;
    scene.add(scanMesh);
  }

  function draw() {
    // One view, or two side by side through the same camera: left what the view shows (the
    // mesh in its mode, its extras), right the scan alone.
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (!state.split) {
      renderer.setScissorTest(false);
      renderer.setViewport(0, 0, w, h);
      renderer.render(scene, camera);
      state.views = 1;
      return;
    }
    renderer.setScissorTest(true);
    renderer.setViewport(0, 0, w / 2, h);
    renderer.setScissor(0, 0, w / 2, h);
    renderer.render(scene, camera);
    const shown = scene.children.filter((o) => o.visible && !o.isLight && o !== camera);
    for (const object of shown) object.visible = false;
    scanMesh.visible = true;
    renderer.setViewport(w / 2, 0, w - w / 2, h);
    renderer.setScissor(w / 2, 0, w - w / 2, h);
    renderer.render(scene, camera);
    scanMesh.visible = false;
    for (const object of shown) object.visible = true;
    state.views = 2;
  }

  function addExtras() {
    if (data.cloud) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(buffer(data.cloud.positions, Float32Array), 3));
      geometry.setAttribute("color", new THREE.BufferAttribute(buffer(data.cloud.colours, Uint8Array), 3, true));
      extras.cloud = new THREE.Points(geometry, new THREE.PointsMaterial(
        {size: 2, sizeAttenuation: false, vertexColors: true}));
    }
    if (data.cameras) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(buffer(data.cameras.lines, Float32Array), 3));
      extras.cameras = new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({color: 0x2060c0}));
    }
    for (const object of Object.values(extras)) {
      object.visible = false;
      scene.add(object);
    }
  }

  function frame(geometry) {
    geometry.computeBoundingSphere();
    const sphere = geometry.boundingSphere;
    // Face the viewer the way the capture's cameras faced the head (their mean direction).
    const towards = new THREE.Vector3(...(data.view_direction || [0, 0, 1])).normalize();
    const distance = sphere.radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.1;
    camera.position.copy(sphere.center).addScaledVector(towards, distance);
    camera.up.set(...(data.view_up || [0, 1, 0]));
    camera.near = distance / 100;
    camera.far = distance * 100;
    camera.updateProjectionMatrix();
    controls.target.copy(sphere.center);
    controls.update();
  }

  function seamCopies(count) {
    // meshVertex from the glTF's userData (on the mesh, its geometry or a parent), the
    // identity where it has none (a mesh without seams) or where it does not fit.
    let found = {};
    for (let o = mesh; o; o = o.parent)
      if ("seam_vertex" in o.userData) { found = o.userData; break; }
    if ("seam_vertex" in mesh.geometry.userData) found = mesh.geometry.userData;
    const seam = Array.isArray(found.seam_vertex) ? found.seam_vertex : [];
    const n = Number.isInteger(found.template_vertices) ? found.template_vertices : count;
    const fits = n + seam.length === count &&
      seam.every((v) => Number.isInteger(v) && v >= 0 && v < n);
    meshVertices = fits ? n : count;
    meshVertex = new Uint32Array(count);
    for (let i = 0; i < count; i++) meshVertex[i] = fits && i >= n ? seam[i - n] : i;
  }

  function spread(values, size) {
    // Per-mesh-vertex values (``size`` each) onto the glTF's vertices; null if they are not
    // one per mesh vertex.
    if (values.length !== size * meshVertices) return null;
    const out = new values.constructor(size * meshVertex.length);
    for (let i = 0; i < meshVertex.length; i++)
      for (let c = 0; c < size; c++) out[size * i + c] = values[size * meshVertex[i] + c];
    return out;
  }

  new THREE.GLTFLoader().parse(bytes(data.mesh_glb).buffer, "", (gltf) => {
    gltf.scene.traverse((object) => { if (object.isMesh && !mesh) mesh = object; });
    const geometry = mesh.geometry;
    // The glTF's normals are the unsplit mesh's (smooth across the seams); recomputed here
    // they would part along them.
    if (!geometry.getAttribute("normal")) geometry.computeVertexNormals();
    const count = geometry.getAttribute("position").count;
    seamCopies(count);
    if (mesh.material.map) {  // its own texture in Colour
      materials.colour = mesh.material;
      materials.colour.side = THREE.DoubleSide;
    }
    colours = {original: geometry.getAttribute("color") ||
               new THREE.BufferAttribute(new Float32Array(count * 3).fill(0.8), 3)};
    if (data.accuracy) {
      const heat = spread(buffer(data.accuracy.colours, Uint8Array), 3);
      if (heat) colours.heat = new THREE.BufferAttribute(heat, 3, true);
      else delete data.accuracy;  // not this mesh's: no heat map rather than a broken draw
    }
    // The mesh alone, in world coordinates (mm), as the cameras and the cloud are.
    mesh.removeFromParent();
    mesh.position.set(0, 0, 0);
    mesh.rotation.set(0, 0, 0);
    mesh.scale.set(1, 1, 1);
    scene.add(mesh);
    addExtras();
    extras.mesh = mesh;  // shown; hidden, the cloud is seen alone (the Mesh switch)
    // The wireframe: the triangles' edges over the surface, on demand.
    extras.wireframe = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial(
      {color: 0x202020, wireframe: true, transparent: true, opacity: 0.35, depthWrite: false}));
    extras.wireframe.visible = false;
    scene.add(extras.wireframe);
    setMode("colour");
    resize();
    frame(geometry);
    state.ready = true;
    stale = true;
  }, (error) => {
    state.reason = "the mesh could not be read";
    console.error("facecap: the mesh could not be read", error);
  });

  for (const button of document.querySelectorAll("[data-mode]"))
    button.addEventListener("click", () => setMode(button.dataset.mode));
  document.getElementById("measure-button").addEventListener(
    "click", () => setMeasuring(!state.measuring));
  for (const button of document.querySelectorAll("[data-preset]"))
    button.addEventListener("click", () => showPreset(button.dataset.preset));
  const slider = document.querySelector("#light input");
  slider.addEventListener("input", () => setLight(Number(slider.value)));
  if (data.scan) document.getElementById("scan-button").addEventListener(
    "click", () => setScan(!state.split));
  for (const button of document.querySelectorAll("[data-toggle]"))
    button.addEventListener("click", () => toggle(button.dataset.toggle));
  (function loop() {
    resize();
    controls.update();  // moves the camera on while a turn is damped ("change": stale)
    if (stale) {
      stale = false;
      draw();
      state.drawn += 1;
      state.still = 0;
    } else {
      state.still += 1;
    }
    requestAnimationFrame(loop);
  })();
})();
