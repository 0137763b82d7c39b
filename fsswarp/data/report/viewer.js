// fsswarp report: a small WebGL viewer of the meshes in the <script id="model-data"> JSON
// (no library, no request). Each mesh: uint16 vertex coordinates quantized in data.box and
// uint16 or uint32 triangle indices, base64. Drag turns, the wheel zooms, a double click
// resets; the legend's boxes show or hide a model; "side by side" / "overlaid" place them.
(function () {
  "use strict";
  const canvas = document.getElementById("viewer");
  const data = JSON.parse(document.getElementById("model-data").textContent);
  const note = document.getElementById("viewer-note");
  const gl = canvas.getContext("webgl", {preserveDrawingBuffer: true, antialias: true});
  if (!gl) {
    canvas.dataset.state = "no-webgl";
    note.textContent = "This browser offers no WebGL: the 3-D view cannot be drawn here.";
    return;
  }
  const wide = gl.getExtension("OES_element_index_uint");

  function bytes(text) {
    const raw = atob(text);
    const out = new Uint8Array(raw.length);
    for (let i = 0; i < raw.length; i++) out[i] = raw.charCodeAt(i);
    return out;
  }

  const lo = data.box.min, hi = data.box.max;
  const size = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
  const centre = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
  const radius = 0.5 * Math.hypot(size[0], size[1], size[2]);

  const meshes = data.meshes.map(function (entry) {
    const q = new Uint16Array(bytes(entry.positions).buffer);
    const count = q.length / 3;
    const positions = new Float32Array(q.length);
    for (let i = 0; i < q.length; i++) {
      const axis = i % 3;
      positions[i] = lo[axis] + (q[i] / 65535) * size[axis] - centre[axis];
    }
    const raw = bytes(entry.indices);
    const indices = entry.index_bytes === 4 ? new Uint32Array(raw.buffer) : new Uint16Array(raw.buffer);
    const normals = new Float32Array(positions.length);
    for (let f = 0; f < indices.length; f += 3) {
      const a = 3 * indices[f], b = 3 * indices[f + 1], c = 3 * indices[f + 2];
      const u = [positions[b] - positions[a], positions[b + 1] - positions[a + 1], positions[b + 2] - positions[a + 2]];
      const v = [positions[c] - positions[a], positions[c + 1] - positions[a + 1], positions[c + 2] - positions[a + 2]];
      const n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
      for (const k of [a, b, c]) {
        normals[k] += n[0]; normals[k + 1] += n[1]; normals[k + 2] += n[2];
      }
    }
    const mesh = {label: entry.label, colour: entry.colour, count: indices.length, visible: true,
                  type: entry.index_bytes === 4 ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT, vertices: count};
    mesh.position = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, mesh.position);
    gl.bufferData(gl.ARRAY_BUFFER, positions, gl.STATIC_DRAW);
    mesh.normal = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, mesh.normal);
    gl.bufferData(gl.ARRAY_BUFFER, normals, gl.STATIC_DRAW);
    mesh.index = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, mesh.index);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    mesh.drawable = entry.index_bytes !== 4 || wide !== null;
    return mesh;
  });

  function shader(type, source) {
    const s = gl.createShader(type);
    gl.shaderSource(s, source);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  const program = gl.createProgram();
  gl.attachShader(program, shader(gl.VERTEX_SHADER, [
    "attribute vec3 position; attribute vec3 normal;",
    "uniform mat4 projection; uniform mat4 view; uniform vec3 offset;",
    "varying vec3 world; varying vec3 bent;",
    "void main() { world = position + offset; bent = normal;",
    "  gl_Position = projection * view * vec4(world, 1.0); }"].join("\n")));
  gl.attachShader(program, shader(gl.FRAGMENT_SHADER, [
    "precision mediump float;",
    "uniform vec3 colour; uniform vec3 eye; uniform float lit;",
    "varying vec3 world; varying vec3 bent;",
    "void main() { vec3 n = normalize(bent); vec3 l = normalize(eye - world);",
    "  float shade = mix(1.0, 0.28 + 0.72 * abs(dot(n, l)), lit);",
    "  gl_FragColor = vec4(colour * shade, 1.0); }"].join("\n")));
  gl.linkProgram(program);
  gl.useProgram(program);
  const where = {};
  for (const name of ["projection", "view", "offset", "colour", "eye", "lit"]) {
    where[name] = gl.getUniformLocation(program, name);
  }
  const attribute = {position: gl.getAttribLocation(program, "position"), normal: gl.getAttribLocation(program, "normal")};

  const axes = gl.createBuffer();  // x, y, z from the box's lowest corner, 30% of its largest side
  const arm = 0.3 * Math.max(size[0], size[1], size[2]);
  const corner = [lo[0] - centre[0], lo[1] - centre[1], lo[2] - centre[2]];
  const axisPoints = [];
  for (let k = 0; k < 3; k++) {
    const end = corner.slice();
    end[k] += arm;
    axisPoints.push(...corner, ...end);
  }
  gl.bindBuffer(gl.ARRAY_BUFFER, axes);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(axisPoints), gl.STATIC_DRAW);

  const home = {yaw: -0.55, pitch: 0.35, distance: 1.0};
  const camera = Object.assign({}, home);
  let layout = "side";

  function offsets() {
    const shown = meshes.filter(function (m) { return m.visible; });
    const step = 1.25 * size[0];
    const result = new Map();
    shown.forEach(function (m, i) {
      result.set(m, layout === "side" ? [(i - (shown.length - 1) / 2) * step, 0, 0] : [0, 0, 0]);
    });
    return {map: result, span: layout === "side" ? Math.max(0, shown.length - 1) * step : 0};
  }

  function perspective(fov, aspect, near, far) {
    const f = 1 / Math.tan(fov / 2);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
  }

  function lookAt(eye, target, up) {
    const z = normalise([eye[0] - target[0], eye[1] - target[1], eye[2] - target[2]]);
    const x = normalise(cross(up, z));
    const y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
            -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function normalise(a) { const n = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / n, a[1] / n, a[2] / n]; }

  function draw() {
    const ratio = window.devicePixelRatio || 1;
    const width = Math.max(1, Math.round(canvas.clientWidth * ratio));
    const height = Math.max(1, Math.round(canvas.clientHeight * ratio));
    if (canvas.width !== width || canvas.height !== height) {
      canvas.width = width;
      canvas.height = height;
    }
    gl.viewport(0, 0, width, height);
    gl.clearColor(1, 1, 1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    const placed = offsets();
    const reach = (radius + placed.span / 2) * 1.9 * camera.distance;
    const eye = [reach * Math.cos(camera.pitch) * Math.sin(camera.yaw),
                 -reach * Math.cos(camera.pitch) * Math.cos(camera.yaw),
                 reach * Math.sin(camera.pitch)];
    gl.uniformMatrix4fv(where.projection, false, perspective(0.7, width / height, reach / 50, reach * 4));
    gl.uniformMatrix4fv(where.view, false, lookAt(eye, [0, 0, 0], [0, 0, 1]));
    gl.uniform3fv(where.eye, eye);
    gl.uniform1f(where.lit, 1);
    let drawn = 0;
    for (const mesh of meshes) {
      if (!mesh.visible || !mesh.drawable) continue;
      gl.uniform3fv(where.offset, placed.map.get(mesh));
      gl.uniform3fv(where.colour, mesh.colour);
      gl.bindBuffer(gl.ARRAY_BUFFER, mesh.position);
      gl.enableVertexAttribArray(attribute.position);
      gl.vertexAttribPointer(attribute.position, 3, gl.FLOAT, false, 0, 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, mesh.normal);
      gl.enableVertexAttribArray(attribute.normal);
      gl.vertexAttribPointer(attribute.normal, 3, gl.FLOAT, false, 0, 0);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, mesh.index);
      gl.drawElements(gl.TRIANGLES, mesh.count, mesh.type, 0);
      drawn += 1;
    }
    gl.uniform1f(where.lit, 0);
    gl.disableVertexAttribArray(attribute.normal);
    gl.vertexAttrib3f(attribute.normal, 0, 0, 1);
    gl.bindBuffer(gl.ARRAY_BUFFER, axes);
    gl.vertexAttribPointer(attribute.position, 3, gl.FLOAT, false, 0, 0);
    const first = placed.map.size ? placed.map.values().next().value : [0, 0, 0];
    gl.uniform3fv(where.offset, first);
    [[0.85, 0.1, 0.1], [0.1, 0.6, 0.1], [0.1, 0.25, 0.9]].forEach(function (colour, k) {
      gl.uniform3fv(where.colour, colour);
      gl.drawArrays(gl.LINES, 2 * k, 2);
    });
    canvas.dataset.state = "drawn";
    canvas.dataset.meshesDrawn = String(drawn);
  }

  let dragging = null;
  canvas.addEventListener("pointerdown", function (event) {
    dragging = [event.clientX, event.clientY];
    canvas.setPointerCapture(event.pointerId);
  });
  canvas.addEventListener("pointermove", function (event) {
    if (!dragging) return;
    camera.yaw += 0.01 * (event.clientX - dragging[0]);
    camera.pitch = Math.max(-1.5, Math.min(1.5, camera.pitch + 0.01 * (event.clientY - dragging[1])));
    dragging = [event.clientX, event.clientY];
    draw();
  });
  canvas.addEventListener("pointerup", function () { dragging = null; });
  canvas.addEventListener("wheel", function (event) {
    event.preventDefault();
    camera.distance = Math.max(0.15, Math.min(6, camera.distance * Math.exp(0.001 * event.deltaY)));
    draw();
  }, {passive: false});
  canvas.addEventListener("dblclick", function () { Object.assign(camera, home); draw(); });
  document.querySelectorAll("input[data-mesh]").forEach(function (box) {
    box.addEventListener("change", function () {
      meshes.forEach(function (m) { if (m.label === box.dataset.mesh) m.visible = box.checked; });
      draw();
    });
  });
  document.querySelectorAll("button[data-layout]").forEach(function (button) {
    button.addEventListener("click", function () {
      layout = button.dataset.layout;
      document.querySelectorAll("button[data-layout]").forEach(function (b) {
        b.setAttribute("aria-pressed", String(b === button));
      });
      draw();
    });
  });
  window.addEventListener("resize", draw);
  if (meshes.some(function (m) { return !m.drawable; })) {
    note.textContent = "This browser cannot draw meshes of more than 65,536 vertices; those are left out.";
  }
  draw();
})();
