// report.html's 3-D view (bonecad.export.viewer): decodes the embedded meshes, colours them by
// signed deviation or shows reflection lines (zebra), orbits/zooms with three.js TrackballControls,
// toggles meshes, seams, region-boundary planes and frame axes.
(function () {
  const data = JSON.parse(document.getElementById('view-data').textContent);
  const canvas = document.getElementById('view-canvas');
  const renderer = new THREE.WebGLRenderer({canvas: canvas, antialias: true, preserveDrawingBuffer: true});
  renderer.setClearColor(0xffffff, 1);
  const scene = new THREE.Scene();
  const decode = (b64, Type) => {  // a plain loop: Uint8Array.from with a callback is ~10x slower
    const text = atob(b64);
    const bytes = new Uint8Array(text.length);
    for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
    return new Type(bytes.buffer);
  };
  const frame = data.frame;
  const lateral = frame ? new THREE.Vector3(...frame.lateral) : new THREE.Vector3(1, 0, 0);
  const anterior = frame ? new THREE.Vector3(...frame.anterior) : new THREE.Vector3(0, 1, 0);
  const proximal = frame ? new THREE.Vector3(...frame.proximal) : new THREE.Vector3(0, 0, 1);
  let limit = data.limit_mm;
  // diverging blue - white - red (ColorBrewer RdBu ends)
  const colour = (d, out, i) => {
    const t = Math.max(-1, Math.min(1, d / limit));
    const lo = [33, 102, 172], mid = [247, 247, 247], hi = [178, 24, 43];
    const end = t < 0 ? lo : hi, a = Math.abs(t);
    for (let k = 0; k < 3; k++) out[3 * i + k] = (mid[k] + (end[k] - mid[k]) * a) / 255;
  };
  // zebra: the eye's view ray reflected about the pixel's normal (view space); the band is the angle of
  // the reflection to the camera's up axis, in `stripes` bands over 180 degrees, averaged over the pixel
  // (fwidth) so dense stripes fade to grey instead of aliasing
  const zebraMaterial = new THREE.ShaderMaterial({
    uniforms: {stripes: {value: 40.0}},
    side: THREE.DoubleSide,
    polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1,  // the seams' lines stay in front
    extensions: {derivatives: true},
    vertexShader: `varying vec3 vNormal; varying vec3 vView;
      void main() {
        vec4 p = modelViewMatrix * vec4(position, 1.0);
        vView = p.xyz; vNormal = normalMatrix * normal;
        gl_Position = projectionMatrix * p;
      }`,
    fragmentShader: `uniform float stripes; varying vec3 vNormal; varying vec3 vView;
      float integral(float x) { float h = floor(x / 2.0); return h + clamp(x - 2.0 * h - 1.0, 0.0, 1.0); }
      void main() {
        vec3 n = normalize(vNormal); vec3 v = normalize(vView);
        if (dot(n, v) > 0.0) n = -n;
        vec3 r = reflect(v, n);
        float phase = stripes * acos(clamp(r.y, -1.0, 1.0)) / 3.14159265;
        float w = max(fwidth(phase), 1e-4);
        float light = (integral(phase + 0.5 * w) - integral(phase - 0.5 * w)) / w;
        float grey = (0.08 + 0.87 * light) * (0.55 + 0.45 * abs(n.z));
        gl_FragColor = vec4(vec3(grey), 1.0);
      }`,
  });
  const surface = {side: THREE.DoubleSide, polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1};
  const plainMaterial = new THREE.MeshLambertMaterial({color: 0xd8d8d8, ...surface});
  // screen right when seen from the front with proximal up: the meshes' row runs along it
  const right = new THREE.Vector3().crossVectors(anterior.clone().negate(), proximal).normalize();
  const meshes = [];
  let offset = 0, widest = 0;
  const box = new THREE.Box3();
  data.meshes.forEach((m) => {
    const geometry = new THREE.BufferGeometry();
    const positions = decode(m.positions, Float32Array);
    geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
    geometry.setIndex(new THREE.BufferAttribute(decode(m.indices, Uint32Array), 1));
    geometry.computeVertexNormals();
    geometry.setAttribute('color', new THREE.BufferAttribute(new Float32Array(positions.length), 3));
    const deviation = {};
    for (const k in m.deviation) deviation[k] = decode(m.deviation[k], Float32Array);
    const material = new THREE.MeshLambertMaterial({vertexColors: true, ...surface});
    const mesh = new THREE.Mesh(geometry, material);
    geometry.computeBoundingBox();
    const b = geometry.boundingBox;
    const corners = [];
    for (let c = 0; c < 8; c++) corners.push(new THREE.Vector3(c & 1 ? b.max.x : b.min.x,
      c & 2 ? b.max.y : b.min.y, c & 4 ? b.max.z : b.min.z).dot(right));
    widest = Math.max(widest, Math.max(...corners) - Math.min(...corners));
    meshes.push({mesh: mesh, deviation: deviation, colours: material, seams: m.seams});
    scene.add(mesh);
  });
  meshes.forEach((m, i) => {
    m.mesh.position.copy(right.clone().multiplyScalar(1.25 * widest * i));
    box.expandByObject(m.mesh);
  });
  // the region boundaries: a translucent square across each bone, normal to the proximal axis
  const planes = [];
  if (frame) {
    const origin = new THREE.Vector3(...frame.origin);
    // right-handed whichever the side (a left bone's frame is mirrored): the plane's normal is proximal
    const across = new THREE.Vector3().crossVectors(proximal, lateral);
    const basis = new THREE.Matrix4().makeBasis(lateral, across, proximal);
    meshes.forEach((m) => data.boundaries_mm.forEach((height) => {
      const plane = new THREE.Mesh(new THREE.PlaneGeometry(0.9 * widest, 0.9 * widest),
        new THREE.MeshBasicMaterial({color: 0x7b3294, transparent: true, opacity: 0.3, side: THREE.DoubleSide,
                                     depthWrite: false}));
      plane.setRotationFromMatrix(basis);
      plane.position.copy(origin.clone().add(proximal.clone().multiplyScalar(height)));
      m.mesh.add(plane);
      planes.push(plane);
    }));
  }
  const axes = new THREE.Group();
  if (frame) {
    const origin = new THREE.Vector3(...frame.origin);
    const length = 0.25 * box.getSize(new THREE.Vector3()).length();
    [[lateral, 0xd62728], [anterior, 0x2ca02c], [proximal, 0x1f77b4]].forEach(([axis, hex]) => {
      const g = new THREE.BufferGeometry().setFromPoints([origin, origin.clone().add(axis.clone().multiplyScalar(length))]);
      axes.add(new THREE.Line(g, new THREE.LineBasicMaterial({color: hex})));
    });
    scene.add(axes);
  }
  const recolour = () => {
    const which = document.getElementById('colour-by').value;
    meshes.forEach((m) => {
      const d = m.deviation[which] || Object.values(m.deviation)[0];
      const c = m.mesh.geometry.getAttribute('color');
      for (let i = 0; i < d.length; i++) colour(d[i], c.array, i);
      c.needsUpdate = true;
    });
    document.getElementById('scale-lo').textContent = (-limit).toFixed(2);
    document.getElementById('scale-hi').textContent = '+' + limit.toFixed(2);
  };
  scene.add(new THREE.AmbientLight(0xffffff, 0.45));
  const light = new THREE.DirectionalLight(0xffffff, 0.7);
  scene.add(light);
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const camera = new THREE.PerspectiveCamera(30, canvas.width / canvas.height, sphere.radius / 100, sphere.radius * 20);
  const controls = new THREE.TrackballControls(camera, canvas);
  camera.up.copy(proximal);
  camera.position.copy(sphere.center.clone().add(anterior.clone().multiplyScalar(3.3 * sphere.radius)));
  controls.target.copy(sphere.center);
  controls.update();
  controls.rotateSpeed = 2.0;
  const render = () => { light.position.copy(camera.position); renderer.render(scene, camera); };
  controls.addEventListener('change', render);
  const animate = () => { requestAnimationFrame(animate); controls.update(); };
  document.querySelectorAll('#viewer3d input[data-mesh]').forEach((box) => box.addEventListener('change', () => {
    meshes[Number(box.dataset.mesh)].mesh.visible = box.checked; render();
  }));
  document.getElementById('show-frame').addEventListener('change', (e) => { axes.visible = e.target.checked; render(); });
  document.getElementById('show-planes').addEventListener('change', (e) => {
    planes.forEach((p) => { p.visible = e.target.checked; }); render();
  });
  const showSeams = document.getElementById('show-seams');
  const reseam = () => {  // the seams' lines are built when first shown (they are off at load)
    meshes.forEach((m) => {
      if (showSeams.checked && m.seams) {
        const geometry = new THREE.BufferGeometry();
        geometry.setAttribute('position', new THREE.BufferAttribute(decode(m.seams, Float32Array), 3));
        const lines = new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({color: 0x111111}));
        lines.name = 'seams';
        m.mesh.add(lines);
        m.seams = null;
      }
      const lines = m.mesh.getObjectByName('seams');
      if (lines) lines.visible = showSeams.checked;
    });
    render();
  };
  showSeams.addEventListener('change', reseam);
  const shading = document.getElementById('shading');
  const stripesInput = document.getElementById('stripes');
  const reshade = () => {
    const chosen = {deviation: null, zebra: zebraMaterial, plain: plainMaterial}[shading.value];
    meshes.forEach((m) => { m.mesh.material = chosen || m.colours; });
    const n = parseFloat(stripesInput.value);
    if (n > 0) zebraMaterial.uniforms.stripes.value = n;
    render();
  };
  shading.addEventListener('change', reshade);
  stripesInput.addEventListener('change', reshade);
  const limitInput = document.getElementById('colour-limit');
  limitInput.value = limit.toFixed(2);
  limitInput.addEventListener('change', () => {
    const v = parseFloat(limitInput.value);
    if (v > 0) { limit = v; recolour(); render(); }
  });
  document.getElementById('colour-by').addEventListener('change', () => { recolour(); render(); });
  recolour();
  reseam();
  animate();
  canvas.dataset.drawn = 'yes';
  canvas.dataset.drawnMs = Math.round(performance.now());  // since navigation start: the page's load and first frame
})();
