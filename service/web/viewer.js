"use strict";
// PointViewer: point clouds on a <canvas>, drawn with WebGL, or projected onto a 2D canvas when WebGL is
// unavailable (e.g. a browser without GPU access). Orbit camera: drag to turn, wheel to zoom; with the canvas
// focused, arrow keys turn, + / = and - zoom, Home or 0 resets. The view is mirrored in canvas.dataset.view.
// Matrices are 4x4, column-major Float32Array(16) as WebGL expects; a cloud is a Float32Array [n * 3].
(function (global) {
  const VERTEX_SHADER = `
    attribute vec3 position;
    uniform mat4 mvp;
    uniform float size;
    void main() { gl_Position = mvp * vec4(position, 1.0); gl_PointSize = size; }`;
  const FRAGMENT_SHADER = `
    precision mediump float;
    uniform vec3 color;
    void main() { gl_FragColor = vec4(color, 1.0); }`;
  const BACKGROUND = [17, 20, 24];
  const PITCH_LIMIT = 1.55; // rad: just short of straight up/down
  const KEY_ORBIT = Math.PI / 36; // rad per arrow key press (5 degrees)
  const KEY_ZOOM = 1.2; // distance factor per + / - press
  // key -> [yaw step, pitch step] in KEY_ORBIT units; each turns as a drag in the arrow's direction
  const ORBIT_KEYS = new Map([["ArrowLeft", [-1, 0]], ["ArrowRight", [1, 0]], ["ArrowUp", [0, -1]], ["ArrowDown", [0, 1]]]);
  const ZOOM_KEYS = new Map([["+", 1 / KEY_ZOOM], ["=", 1 / KEY_ZOOM], ["-", KEY_ZOOM]]); // key -> distance factor
  const RESET_KEYS = new Set(["Home", "0"]);
  // Point clouds (LAS, E57, PTX, maps) are Z-up: world +z is drawn up and the orbit turns about it.
  const Z_UP = (() => { const m = new Float32Array(16); m[0] = 1; m[6] = -1; m[9] = 1; m[15] = 1; return m; })();

  function identity() {
    const m = new Float32Array(16);
    m[0] = m[5] = m[10] = m[15] = 1;
    return m;
  }

  function multiply(a, b) { // a * b
    const out = new Float32Array(16);
    for (let col = 0; col < 4; col++) {
      for (let row = 0; row < 4; row++) {
        let sum = 0;
        for (let k = 0; k < 4; k++) sum += a[k * 4 + row] * b[col * 4 + k];
        out[col * 4 + row] = sum;
      }
    }
    return out;
  }

  function perspective(fovyRad, aspect, near, far) {
    const f = 1 / Math.tan(fovyRad / 2);
    const m = new Float32Array(16);
    m[0] = f / aspect;
    m[5] = f;
    m[10] = (far + near) / (near - far);
    m[11] = -1;
    m[14] = (2 * far * near) / (near - far);
    return m;
  }

  function translation(x, y, z) {
    const m = identity();
    m[12] = x; m[13] = y; m[14] = z;
    return m;
  }

  function rotationX(a) {
    const m = identity(), c = Math.cos(a), s = Math.sin(a);
    m[5] = c; m[6] = s; m[9] = -s; m[10] = c;
    return m;
  }

  function rotationY(a) {
    const m = identity(), c = Math.cos(a), s = Math.sin(a);
    m[0] = c; m[2] = -s; m[8] = s; m[10] = c;
    return m;
  }

  // The model matrix of points p stored relative to their cloud's `origin` (p + origin in the caller's frame), moved by
  // the row-major 4x4 src_to_tgt `rowMajor` (nested arrays, as the API returns it; null: as uploaded) and drawn
  // relative to `centre`: p -> R p + (R origin + t - centre). The shift is formed in doubles, so that clouds in map
  // (UTM) coordinates stay small on the GPU.
  function placedTransform(rowMajor, origin, centre) {
    const m = identity();
    for (let row = 0; row < 3; row++) {
      let shift = (rowMajor ? rowMajor[row][3] : 0) - centre[row];
      for (let col = 0; col < 3; col++) {
        const r = rowMajor ? rowMajor[row][col] : (row === col ? 1 : 0);
        m[col * 4 + row] = r;
        shift += r * origin[col];
      }
      m[12 + row] = shift;
    }
    return m;
  }

  // The bounding box [lo, hi] of a cloud's points as placed (p + origin, moved by rowMajor), in doubles.
  function placedBox(points, origin, rowMajor) {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    const R = rowMajor || [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]];
    for (let i = 0; i < points.length; i += 3) {
      const x = points[i] + origin[0], y = points[i + 1] + origin[1], z = points[i + 2] + origin[2];
      for (let k = 0; k < 3; k++) {
        const v = R[k][0] * x + R[k][1] * y + R[k][2] * z + R[k][3];
        if (v < lo[k]) lo[k] = v;
        if (v > hi[k]) hi[k] = v;
      }
    }
    return [lo, hi];
  }

  function compileProgram(gl) {
    const program = gl.createProgram();
    for (const [kind, text] of [[gl.VERTEX_SHADER, VERTEX_SHADER], [gl.FRAGMENT_SHADER, FRAGMENT_SHADER]]) {
      const shader = gl.createShader(kind);
      gl.shaderSource(shader, text);
      gl.compileShader(shader);
      if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
      gl.attachShader(program, shader);
    }
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    return program;
  }

  class PointViewer {
    // options.renderer: "webgl" (default, falls back to "2d") or "2d".
    constructor(canvas, options = {}) {
      this.canvas = canvas;
      this.clouds = []; // {name, points (relative to origin), origin, pose, color [r, g, b] 0-255, model (Float32Array)}
      this.centre = [0, 0, 0];
      this.radius = 1;
      this.yaw = 0.6;
      this.pitch = 0.35;
      this.distance = 3;
      this.pending = false;
      this.gl = null;
      if (options.renderer !== "2d") this.initWebGL();
      if (!this.gl) this.ctx = canvas.getContext("2d");
      this.renderer = this.gl ? "WebGL" : "2D canvas";
      this.bindControls();
      new ResizeObserver(() => this.draw()).observe(canvas);
    }

    initWebGL() {
      const attributes = {antialias: false, preserveDrawingBuffer: true};
      const gl = this.canvas.getContext("webgl", attributes) || this.canvas.getContext("experimental-webgl", attributes);
      if (!gl) return;
      try {
        this.program = compileProgram(gl);
      } catch (err) {
        console.warn("WebGL shaders failed; drawing in 2D", err);
        return;
      }
      this.locations = {
        position: gl.getAttribLocation(this.program, "position"),
        mvp: gl.getUniformLocation(this.program, "mvp"),
        size: gl.getUniformLocation(this.program, "size"),
        color: gl.getUniformLocation(this.program, "color"),
      };
      this.gl = gl;
    }

    // clouds: [{name, points: Float32Array [n * 3] relative to origin, origin: [3] (default 0), color}]; the view
    // centres on their common bounding box.
    setClouds(clouds) {
      const gl = this.gl;
      for (const old of this.clouds) if (gl && old.buffer) gl.deleteBuffer(old.buffer);
      this.clouds = clouds.map((cloud) => {
        const entry = {name: cloud.name, points: cloud.points, origin: cloud.origin || [0, 0, 0], pose: null,
                       color: cloud.color, model: identity(), visible: true};
        if (gl) {
          entry.buffer = gl.createBuffer();
          gl.bindBuffer(gl.ARRAY_BUFFER, entry.buffer);
          gl.bufferData(gl.ARRAY_BUFFER, entry.points, gl.STATIC_DRAW);
        }
        return entry;
      });
      this.frame();
      this.resetView();
    }

    // The row-major 4x4 pose to draw the named cloud with (null: as given); the view centres on the clouds as now
    // placed (a scan moved into a map far from where it was uploaded is framed with the map), keeping its angle and
    // its distance in cloud radii.
    setPose(name, rowMajor) {
      const cloud = this.clouds.find((c) => c.name === name);
      if (!cloud) return;
      cloud.pose = rowMajor;
      const radius = this.radius;
      this.frame();
      this.distance *= this.radius / radius;
      this.draw();
    }

    // Centre and radius of the clouds' common bounding box as placed, and each cloud's model matrix about that centre.
    frame() {
      const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
      for (const cloud of this.clouds) {
        const [cloudLo, cloudHi] = placedBox(cloud.points, cloud.origin, cloud.pose);
        for (let k = 0; k < 3; k++) {
          lo[k] = Math.min(lo[k], cloudLo[k]);
          hi[k] = Math.max(hi[k], cloudHi[k]);
        }
      }
      const empty = !(hi[0] >= lo[0]);
      this.centre = empty ? [0, 0, 0] : lo.map((v, k) => (v + hi[k]) / 2);
      this.radius = empty ? 1 : Math.max(1e-9, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
      for (const cloud of this.clouds) cloud.model = placedTransform(cloud.pose, cloud.origin, this.centre);
    }

    resetView() {
      this.yaw = 0.6;
      this.pitch = 0.35;
      this.distance = 2.6 * this.radius;
      this.draw();
    }

    // Turn the camera by dYaw, dPitch (rad); pitch stays within +-PITCH_LIMIT.
    orbit(dYaw, dPitch) {
      this.yaw += dYaw;
      this.pitch = Math.max(-PITCH_LIMIT, Math.min(PITCH_LIMIT, this.pitch + dPitch));
      this.draw();
    }

    // Multiply the camera distance by factor (> 1: farther), within 0.05-50 cloud radii.
    zoom(factor) {
      this.distance = Math.max(this.radius * 0.05, Math.min(this.radius * 50, this.distance * factor));
      this.draw();
    }

    bindControls() {
      const canvas = this.canvas;
      let last = null;
      canvas.addEventListener("pointerdown", (e) => {
        last = [e.clientX, e.clientY];
        canvas.setPointerCapture(e.pointerId);
      });
      canvas.addEventListener("pointermove", (e) => {
        if (!last) return;
        this.orbit((e.clientX - last[0]) * 0.01, (e.clientY - last[1]) * 0.01);
        last = [e.clientX, e.clientY];
      });
      const release = () => { last = null; };
      canvas.addEventListener("pointerup", release);
      canvas.addEventListener("pointercancel", release);
      canvas.addEventListener("wheel", (e) => {
        e.preventDefault();
        this.zoom(Math.exp(e.deltaY * 0.001));
      }, {passive: false});
      // Keys reach this listener only while the canvas has focus; browser shortcuts (Ctrl/Alt/Meta) pass through,
      // and only the keys handled here lose their default (page scrolling).
      canvas.addEventListener("keydown", (e) => {
        if (e.ctrlKey || e.altKey || e.metaKey) return;
        const turn = ORBIT_KEYS.get(e.key);
        if (turn) this.orbit(turn[0] * KEY_ORBIT, turn[1] * KEY_ORBIT);
        else if (ZOOM_KEYS.has(e.key)) this.zoom(ZOOM_KEYS.get(e.key));
        else if (RESET_KEYS.has(e.key)) this.resetView();
        else return;
        e.preventDefault();
      });
    }

    viewProjection() {
      const canvas = this.canvas;
      const aspect = canvas.width / Math.max(1, canvas.height);
      const near = Math.max(this.distance - 2 * this.radius, this.distance * 0.01);
      const far = this.distance + 2 * this.radius;
      const view = multiply(translation(0, 0, -this.distance),
        multiply(rotationX(this.pitch), multiply(rotationY(this.yaw), Z_UP)));
      return multiply(perspective(Math.PI / 4, aspect, near, far), view);
    }

    draw() {
      const deg = (rad) => Math.round(rad * 180 / Math.PI * 100) / 100;
      this.canvas.dataset.view = JSON.stringify({yaw_deg: deg(this.yaw), pitch_deg: deg(this.pitch),
        distance: Number(this.distance.toPrecision(6))}); // for scripts and tests: the camera as drawn
      if (this.pending) return;
      this.pending = true;
      requestAnimationFrame(() => {
        this.pending = false;
        this.resize();
        if (this.gl) this.drawWebGL(); else this.draw2D();
      });
    }

    resize() {
      const scale = window.devicePixelRatio || 1;
      const width = Math.max(1, Math.round(this.canvas.clientWidth * scale));
      const height = Math.max(1, Math.round(this.canvas.clientHeight * scale));
      if (this.canvas.width !== width || this.canvas.height !== height) {
        this.canvas.width = width;
        this.canvas.height = height;
      }
    }

    pointSize() {
      return Math.max(2, Math.round(2 * (window.devicePixelRatio || 1)));
    }

    drawWebGL() {
      const gl = this.gl, loc = this.locations;
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
      gl.clearColor(BACKGROUND[0] / 255, BACKGROUND[1] / 255, BACKGROUND[2] / 255, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      gl.enable(gl.DEPTH_TEST);
      gl.useProgram(this.program);
      gl.uniform1f(loc.size, this.pointSize());
      const vp = this.viewProjection();
      for (const cloud of this.clouds) {
        if (!cloud.visible) continue;
        gl.uniformMatrix4fv(loc.mvp, false, multiply(vp, cloud.model));
        gl.uniform3f(loc.color, cloud.color[0] / 255, cloud.color[1] / 255, cloud.color[2] / 255);
        gl.bindBuffer(gl.ARRAY_BUFFER, cloud.buffer);
        gl.enableVertexAttribArray(loc.position);
        gl.vertexAttribPointer(loc.position, 3, gl.FLOAT, false, 0, 0);
        gl.drawArrays(gl.POINTS, 0, cloud.points.length / 3);
      }
    }

    draw2D() { // the same projection, written pixel by pixel with a depth buffer
      const width = this.canvas.width, height = this.canvas.height;
      const image = this.ctx.createImageData(width, height);
      const rgba = image.data;
      for (let i = 0; i < rgba.length; i += 4) {
        rgba[i] = BACKGROUND[0]; rgba[i + 1] = BACKGROUND[1]; rgba[i + 2] = BACKGROUND[2]; rgba[i + 3] = 255;
      }
      const depth = new Float32Array(width * height).fill(Infinity);
      const half = Math.floor(this.pointSize() / 2), size = this.pointSize();
      const vp = this.viewProjection();
      for (const cloud of this.clouds) {
        if (!cloud.visible) continue;
        const m = multiply(vp, cloud.model), p = cloud.points, [r, g, b] = cloud.color;
        for (let i = 0; i < p.length; i += 3) {
          const x = p[i], y = p[i + 1], z = p[i + 2];
          const w = m[3] * x + m[7] * y + m[11] * z + m[15];
          if (w <= 0) continue;
          const nz = (m[2] * x + m[6] * y + m[10] * z + m[14]) / w;
          if (nz < -1 || nz > 1) continue;
          const px = Math.round(((m[0] * x + m[4] * y + m[8] * z + m[12]) / w * 0.5 + 0.5) * width) - half;
          const py = Math.round((0.5 - (m[1] * x + m[5] * y + m[9] * z + m[13]) / w * 0.5) * height) - half;
          for (let dy = 0; dy < size; dy++) {
            const row = py + dy;
            if (row < 0 || row >= height) continue;
            for (let dx = 0; dx < size; dx++) {
              const col = px + dx;
              if (col < 0 || col >= width) continue;
              const at = row * width + col;
              if (nz >= depth[at]) continue;
              depth[at] = nz;
              rgba[at * 4] = r; rgba[at * 4 + 1] = g; rgba[at * 4 + 2] = b;
            }
          }
        }
      }
      this.ctx.putImageData(image, 0, 0);
    }
  }

  global.PointViewer = PointViewer;
})(window);
