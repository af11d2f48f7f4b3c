// The capture page's 3D view: the fitted mesh (glTF) to turn, zoom and light, in its own
// colours, plain, or coloured by its accuracy against the scan; the fused cloud and the
// keyframe cameras on demand. Reads the page's JSON (id "facecap-data"); THREE is the
// vendored three.js bundle. Sets window.facecap = {ready, reason, mode, setMode, toggle}:
// ready once the mesh is shown, reason when it cannot be.
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
  scene.add(new THREE.HemisphereLight(0xffffff, 0x606060, 1.6));
  const headlight = new THREE.DirectionalLight(0xffffff, 1.8);
  headlight.position.set(0.4, 0.6, 1.0);  // follows the viewer: the side facing it is lit
  camera.add(headlight);
  const controls = new THREE.OrbitControls(camera, canvas);
  controls.enableDamping = true;
  const state = {ready: false, mode: "colour", setMode, toggle};
  window.facecap = state;
  // Drawn when something changed (a turn, a zoom, a mode, a size), not every frame: an open
  // page idles rather than keeping a core (or a laptop's GPU) busy.
  let stale = true;
  controls.addEventListener("change", () => { stale = true; });

  function resize() {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * renderer.getPixelRatio()) ||
        canvas.height !== Math.round(h * renderer.getPixelRatio())) {
      renderer.setSize(w, h, false);
      camera.aspect = w / Math.max(h, 1);
      camera.updateProjectionMatrix();
      stale = true;
    }
  }

  function buffer(b64, Type) {
    const raw = bytes(b64);
    return new Type(raw.buffer, raw.byteOffset, raw.byteLength / Type.BYTES_PER_ELEMENT);
  }

  let mesh = null, colours = null;
  // Both sides drawn: the fitted mesh is open (the neck, behind the ears), and its inside,
  // seen through an opening or from behind, is part of what a user turns to look at.
  const materials = {
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
    if (mode !== "plain") mesh.geometry.setAttribute("color", colours[attribute]);
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
    return [(p.x + 1) / 2 * canvas.clientWidth, (1 - p.y) / 2 * canvas.clientHeight];
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

  new THREE.GLTFLoader().parse(bytes(data.mesh_glb).buffer, "", (gltf) => {
    gltf.scene.traverse((object) => { if (object.isMesh && !mesh) mesh = object; });
    const geometry = mesh.geometry;
    geometry.computeVertexNormals();
    const count = geometry.getAttribute("position").count;
    colours = {original: geometry.getAttribute("color") ||
               new THREE.BufferAttribute(new Float32Array(count * 3).fill(0.8), 3)};
    if (data.accuracy) colours.heat = new THREE.BufferAttribute(buffer(data.accuracy.colours, Uint8Array), 3, true);
    // The mesh alone, in world coordinates (mm), as the cameras and the cloud are.
    mesh.removeFromParent();
    mesh.position.set(0, 0, 0);
    mesh.rotation.set(0, 0, 0);
    mesh.scale.set(1, 1, 1);
    scene.add(mesh);
    addExtras();
    extras.mesh = mesh;  // shown; hidden, the cloud is seen alone (the Mesh switch)
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
  for (const button of document.querySelectorAll("[data-toggle]"))
    button.addEventListener("click", () => toggle(button.dataset.toggle));
  (function loop() {
    resize();
    controls.update();  // moves the camera on while a turn is damped ("change": stale)
    if (stale) {
      stale = false;
      renderer.render(scene, camera);
    }
    requestAnimationFrame(loop);
  })();
})();
