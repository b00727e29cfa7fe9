// The WebGL2 viewer: decodes the baked horizon layers as a game shader does and lights the
// surface exactly as the server's CPU preview (src/preview.rs, Scene::render_cancelable) does,
// so the two can be compared pixel for pixel.
//
// Per output pixel (texel centres at integer texel coordinates, one pixel per texel at the
// native size):
//  - normal: central differences of the heights (GET /v1/bakes/{id}/heights, in texels) in texel
//    units, wrapped or clamped per `edge`, the row step flipped per `y_axis` (shade::normals),
//    computed at the four surrounding texels, blended bilinearly and renormalised;
//  - horizon: the two RGBA8 layers sampled with the hardware's bilinear filter (REPEAT for
//    edge=wrap, CLAMP_TO_EDGE for edge=none), squared for encoding=sqrt; the channel-factor cube
//    map sampled with the light direction through a real samplerCube (LINEAR; WebGL2 cube maps
//    are always filtered seamlessly across faces), f = t·2 − 1 (the UNORM zero offset included);
//    s = Σ max(f,0)·h0 + max(−f,0)·h1 (Lengyel eq. 5.3); F = clamp(k·(L_z − s) + 1, 0, 1), 0 for
//    L_z ≤ 0 (SPEC §3.3);
//  - fourier: SPEC §3.4's shader (both `fourier_range`s), at the light's normalised
//    tangent-plane direction;
//  - colour = albedo·(ambient + F·max(N·L, 0)) + (F·ks·(N·H)^24 + env)·HO with HO = saturate(1 +
//    fade·R.z), R = reflect(−V, N), then sRGB as floor(s·255 + 0.5) into an RGBA8 target.
//
// The decode itself (f, s, F and the Fourier form) is not written here: it is the GLSL include
// horizon-bake ships to engines (src/shaders/horizon.glsl), fetched from this server
// (GET /v1/shaders/horizon.glsl, same origin) when this module loads and compiled into the
// fragment shader, so the browser test proves the shipped include against the CPU preview.

import { fetchPublic } from './api.js';

export const ALBEDO = 0.8;
export const AMBIENT = 0.12;
export const SPECULAR = 0.3;
export const SHININESS = 24;
export const ENV_REFLECTION = 0.06;
/** PreviewParams defaults of the server (src/preview.rs). */
export const DEFAULTS = {
  azimuth: 135,
  elevation: 30,
  hardness: 8,
  viewAzimuth: 0,
  viewElevation: 90,
  horizonOcclusion: 1,
  cubeSize: 16,
};

/** (cos e cos a, cos e sin a, sin e) from degrees, as preview::from_angles. */
export function fromAngles(azimuth, elevation) {
  const a = (azimuth * Math.PI) / 180;
  const e = (elevation * Math.PI) / 180;
  return [Math.cos(e) * Math.cos(a), Math.cos(e) * Math.sin(a), Math.sin(e)];
}

function normalize(v) {
  const l = Math.hypot(v[0], v[1], v[2]);
  return l > 0 && Number.isFinite(l) ? [v[0] / l, v[1] / l, v[2] / l] : [0, 0, 1];
}

/** Decodes an image Blob without premultiplying alpha or converting colour spaces. */
export function decodeImage(blob) {
  // Default options corrupt RGBA8 texels whose alpha is 0 (flat ground in a horizon layer).
  return createImageBitmap(blob, { premultiplyAlpha: 'none', colorSpaceConversion: 'none' });
}

/** URL of the shipped GLSL include, beside this module's /ui/ (works under a path prefix). */
export const INCLUDE_URL = new URL('../v1/shaders/horizon.glsl', import.meta.url);

// Fetched once, before app.js runs (a module's top-level await delays its importers). Without
// it the viewer cannot be built: Viewer.create throws, and the page shows the CPU preview.
let includeSource = null;
let includeError = '';
try {
  const res = await fetchPublic(INCLUDE_URL, { cache: 'no-cache' });
  if (!res.ok) throw new Error(`GET ${INCLUDE_URL.pathname} answered ${res.status}`);
  includeSource = await res.text();
} catch (e) {
  includeError = e.message;
}

const VERTEX = `#version 300 es
void main() {
  // One triangle that covers the viewport.
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

const FRAGMENT_HEAD = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp samplerCube;
`;

// Everything of the fragment shader after the include: the viewer's own lighting and debug views.
const FRAGMENT_BODY = `

uniform sampler2D u_layer0;
uniform sampler2D u_layer1;
uniform sampler2D u_four0;
uniform sampler2D u_four1;
uniform sampler2D u_four2;
uniform sampler2D u_heights;   // R32F, texels, row 0 first
uniform samplerCube u_cube;

uniform ivec2 u_size;          // map W, H
uniform vec2 u_scale;          // texels per output pixel
uniform vec2 u_out;            // output width, height in pixels
uniform bool u_wrap;           // edge=wrap
uniform int u_rowStep;         // -1 for y_axis=up, +1 for down
uniform bool u_sqrt;           // encoding=sqrt
uniform int u_mode;            // 0 shaded, 1 layer, 2 channel, 3 normals, 4 cube faces, 5 heights
uniform int u_shading;         // 0 horizon, 1 fourier, 2 none
uniform int u_layerIndex;
uniform int u_channel;
uniform int u_terms;
uniform bool u_fourierExpanded;
uniform vec3 u_light;
uniform vec3 u_half;
uniform vec3 u_view;
uniform vec2 u_lightXY;
uniform float u_hardness;
uniform float u_fade;
uniform vec2 u_hrange;

out vec4 outColor;

ivec2 texel(ivec2 p) {
  // GLSL's % is undefined for negative operands: p >= -2 here (a bilinear footprint's
  // neighbours), so shift by a whole number of periods first.
  if (u_wrap) return (p + 4 * u_size) % u_size;
  return clamp(p, ivec2(0), u_size - 1);
}

float height(ivec2 p) {
  return texelFetch(u_heights, texel(p), 0).r;
}

// shade::normals at texel p.
vec3 texelNormal(ivec2 p) {
  float dx = (height(p + ivec2(1, 0)) - height(p - ivec2(1, 0))) * 0.5;
  float dy = (height(p + ivec2(0, u_rowStep)) - height(p - ivec2(0, u_rowStep))) * 0.5;
  float len = sqrt(dx * dx + dy * dy + 1.0);
  return vec3(-dx / len, -dy / len, 1.0 / len);
}

// Scene::normal: bilinear blend of the per-texel normals, renormalised.
vec3 normalAt(vec2 t) {
  vec2 t0 = floor(t);
  vec2 f = t - t0;
  ivec2 i = ivec2(t0);
  vec3 n00 = texelNormal(i);
  vec3 n10 = texelNormal(i + ivec2(1, 0));
  vec3 n01 = texelNormal(i + ivec2(0, 1));
  vec3 n11 = texelNormal(i + ivec2(1, 1));
  vec3 a = n00 + (n10 - n00) * f.x;
  vec3 b = n01 + (n11 - n01) * f.x;
  vec3 n = a + (b - a) * f.y;
  float l = length(n);
  return l > 0.0 ? n / l : vec3(0.0, 0.0, 1.0);
}

// The layers and the UNORM cube map (cube_N.png) decoded by the include.
float horizonS(vec2 uv) {
  vec4 f = horizon_cube_factors(textureLod(u_cube, u_light, 0.0));
  vec4 h0 = textureLod(u_layer0, uv, 0.0);
  vec4 h1 = textureLod(u_layer1, uv, 0.0);
  if (u_sqrt) {
    h0 = horizon_decode_sqrt(h0);
    h1 = horizon_decode_sqrt(h1);
  }
  return horizon_s(f, h0, h1);
}

// SPEC §3.4's shader, both fourier_ranges, by the include.
float fourierS(vec2 uv) {
  return horizon_fourier(textureLod(u_four0, uv, 0.0), textureLod(u_four1, uv, 0.0).r,
    textureLod(u_four2, uv, 0.0), u_lightXY, u_terms, u_fourierExpanded);
}

// preview::srgb8, returned as the exact UNORM value byte/255.
vec3 srgb8(vec3 v) {
  v = clamp(v, 0.0, 1.0);
  vec3 lo = 12.92 * v;
  vec3 hi = 1.055 * pow(v, vec3(1.0 / 2.4)) - 0.055;
  vec3 s = mix(hi, lo, vec3(lessThanEqual(v, vec3(0.0031308))));
  return floor(s * 255.0 + 0.5) / 255.0;
}

// Direction through (s, t) in [0,1]^2 of a face (cubemap::texel_direction's table).
vec3 faceDirection(int face, vec2 st) {
  float sc = st.x * 2.0 - 1.0;
  float tc = st.y * 2.0 - 1.0;
  if (face == 0) return vec3(1.0, -tc, -sc);
  if (face == 1) return vec3(-1.0, -tc, sc);
  if (face == 2) return vec3(sc, 1.0, tc);
  if (face == 3) return vec3(sc, -1.0, -tc);
  if (face == 4) return vec3(sc, -tc, 1.0);
  return vec3(-sc, -tc, -1.0);
}

void main() {
  // Pixel centre, rows counted from the top as in the CPU image.
  vec2 pc = vec2(gl_FragCoord.x, u_out.y - gl_FragCoord.y);
  vec2 t = pc * u_scale - 0.5;
  vec2 uv = (t + 0.5) / vec2(u_size);

  if (u_mode == 4) {
    // The six faces as their PNG files look (row 0 = t = -1 at the top): +X -X +Y / -Y +Z -Z.
    vec2 g = pc / u_out * vec2(3.0, 2.0);
    ivec2 cell = ivec2(floor(g));
    int face = clamp(cell.y, 0, 1) * 3 + clamp(cell.x, 0, 2);
    vec3 d = faceDirection(face, fract(g));
    vec4 f = textureLod(u_cube, d, 0.0);
    vec3 c = f.rgb;
    if (dot(normalize(d), u_light) > 0.9994) c = vec3(1.0, 1.0, 0.0);   // the light, ~2 deg
    vec2 e = min(fract(g), 1.0 - fract(g)) * u_out / vec2(3.0, 2.0);
    if (min(e.x, e.y) < 0.75) c = vec3(0.1);
    outColor = vec4(c, 1.0);
    return;
  }
  if (u_mode == 1) {
    vec4 h = u_layerIndex == 0 ? textureLod(u_layer0, uv, 0.0) : textureLod(u_layer1, uv, 0.0);
    outColor = vec4(h.rgb, 1.0);
    return;
  }
  if (u_mode == 2) {
    vec4 h = u_channel < 4 ? textureLod(u_layer0, uv, 0.0) : textureLod(u_layer1, uv, 0.0);
    int k = u_channel % 4;
    float v = k == 0 ? h.r : k == 1 ? h.g : k == 2 ? h.b : h.a;
    outColor = vec4(vec3(v), 1.0);
    return;
  }
  vec3 n = normalAt(t);
  if (u_mode == 3) {
    outColor = vec4(n * 0.5 + 0.5, 1.0);
    return;
  }
  if (u_mode == 5) {
    float h = height(ivec2(floor(t + 0.5)));
    float span = u_hrange.y - u_hrange.x;
    outColor = vec4(vec3(span > 0.0 ? (h - u_hrange.x) / span : 0.5), 1.0);
    return;
  }

  vec3 l = u_light;
  float ndl = max(dot(n, l), 0.0);
  float spec = 0.0;
  if (ndl > 0.0) {
    float x = max(dot(n, u_half), 0.0);
    float x2 = x * x;
    float x4 = x2 * x2;
    float x8 = x4 * x4;
    spec = ${SPECULAR.toFixed(6)} * (x8 * x8 * x8);   // (N.H)^${SHININESS}
  }
  float nv = dot(n, u_view);
  float reflZ = 2.0 * nv * n.z - u_view.z;
  float ho = clamp(1.0 + u_fade * reflZ, 0.0, 1.0);
  float F = 1.0;
  if (u_shading == 0) F = horizon_illumination(l.z, horizonS(uv), u_hardness);
  else if (u_shading == 1) F = horizon_illumination(l.z, fourierS(uv), u_hardness);
  float lit = ${ALBEDO.toFixed(6)} * (${AMBIENT.toFixed(6)} + F * ndl) + (F * spec + ${ENV_REFLECTION.toFixed(6)}) * ho;
  outColor = vec4(srgb8(vec3(lit)), 1.0);
}`;

const MODES = { shaded: 0, layer: 1, channel: 2, normals: 3, cube: 4, heights: 5 };
const SHADINGS = { horizon: 0, fourier: 1, none: 2 };

function compile(gl, type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
    throw new Error(`shader: ${gl.getShaderInfoLog(s)}`);
  }
  return s;
}

/** The viewer's fragment shader: its header, the shipped include, its own body. */
function fragmentSource(include) {
  return `${FRAGMENT_HEAD}\n${include}\n${FRAGMENT_BODY}`;
}

/**
 * The WebGL2 renderer of one canvas. `Viewer.create` returns null without WebGL2 and throws
 * when the shader include could not be fetched.
 */
export class Viewer {
  static create(canvas) {
    const gl = canvas.getContext('webgl2', {
      antialias: false,
      premultipliedAlpha: false,
      preserveDrawingBuffer: true,
      depth: false,
      stencil: false,
    });
    if (!gl) return null;
    if (includeSource === null) throw new Error(`the GLSL shader include is missing: ${includeError}`);
    return new Viewer(canvas, gl);
  }

  constructor(canvas, gl) {
    this.canvas = canvas;
    this.gl = gl;
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fragmentSource(includeSource)));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) {
      throw new Error(`program: ${gl.getProgramInfoLog(p)}`);
    }
    this.program = p;
    this.vao = gl.createVertexArray();
    this.loc = {};
    const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const name = gl.getActiveUniform(p, i).name;
      this.loc[name] = gl.getUniformLocation(p, name);
    }
    this.units = { u_layer0: 0, u_layer1: 1, u_four0: 2, u_four1: 3, u_four2: 4, u_heights: 5, u_cube: 6 };
    this.tex = {};
    this.map = null;
    this.fourier = null;
    this.hasLayers = false;
    this.hasCube = false;
    // An empty 1×1 texture in every unit, so the program is valid before data arrives.
    for (const [name, unit] of Object.entries(this.units)) {
      if (name === 'u_cube') continue;
      this.tex[name] = this.texture2d(unit, 1, 1, name === 'u_heights');
    }
    this.tex.u_cube = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + this.units.u_cube);
    gl.bindTexture(gl.TEXTURE_CUBE_MAP, this.tex.u_cube);
    for (let f = 0; f < 6; f++) {
      gl.texImage2D(gl.TEXTURE_CUBE_MAP_POSITIVE_X + f, 0, gl.RGBA8, 1, 1, 0, gl.RGBA,
        gl.UNSIGNED_BYTE, new Uint8Array([128, 128, 128, 128]));
    }
    this.cubeParams();
    this.fbo = null;
  }

  /** The GPU's name (WEBGL_debug_renderer_info when the browser exposes it). */
  rendererName() {
    const gl = this.gl;
    const ext = gl.getExtension('WEBGL_debug_renderer_info');
    const name = ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
    const vendor = ext ? gl.getParameter(ext.UNMASKED_VENDOR_WEBGL) : gl.getParameter(gl.VENDOR);
    return `${name} (${vendor})`;
  }

  maxTextureSize() {
    return this.gl.getParameter(this.gl.MAX_TEXTURE_SIZE);
  }

  unpackRaw() {
    const gl = this.gl;
    gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  }

  texture2d(unit, w, h, isFloat) {
    const gl = this.gl;
    const t = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, t);
    this.unpackRaw();
    if (isFloat) {
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, w, h, 0, gl.RED, gl.FLOAT, new Float32Array(w * h));
    } else {
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, w, h, 0, gl.RGBA, gl.UNSIGNED_BYTE,
        new Uint8Array(w * h * 4).fill(128));
    }
    this.params2d(isFloat, true);
    return t;
  }

  params2d(isFloat, wrap) {
    const gl = this.gl;
    const filter = isFloat ? gl.NEAREST : gl.LINEAR;
    const mode = wrap ? gl.REPEAT : gl.CLAMP_TO_EDGE;
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, filter);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, filter);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, mode);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, mode);
  }

  cubeParams() {
    const gl = this.gl;
    gl.texParameteri(gl.TEXTURE_CUBE_MAP, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_CUBE_MAP, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_CUBE_MAP, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_CUBE_MAP, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  /** Uploads an image (ImageBitmap) into a named 2D unit (RGBA8, bilinear, wrap per edge). */
  uploadImage(name, bitmap) {
    const gl = this.gl;
    gl.activeTexture(gl.TEXTURE0 + this.units[name]);
    gl.bindTexture(gl.TEXTURE_2D, this.tex[name]);
    this.unpackRaw();
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, bitmap);
    this.params2d(false, !this.map || this.map.wrap);
  }

  /** The six cube faces +X, −X, +Y, −Y, +Z, −Z (ImageBitmaps, row 0 = t = −1: no flip). */
  setCube(faces) {
    const gl = this.gl;
    gl.activeTexture(gl.TEXTURE0 + this.units.u_cube);
    gl.bindTexture(gl.TEXTURE_CUBE_MAP, this.tex.u_cube);
    this.unpackRaw();
    faces.forEach((img, f) => {
      gl.texImage2D(gl.TEXTURE_CUBE_MAP_POSITIVE_X + f, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, img);
    });
    this.cubeParams();
    this.hasCube = true;
  }

  /**
   * A bake: {width, height, heights: Float32Array (texels, row 0 first), edge, yAxis, encoding}.
   */
  setMap(m) {
    const gl = this.gl;
    let lo = Infinity;
    let hi = -Infinity;
    for (const v of m.heights) {
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    this.map = { ...m, wrap: m.edge === 'wrap', hmin: lo, hmax: hi };
    gl.activeTexture(gl.TEXTURE0 + this.units.u_heights);
    gl.bindTexture(gl.TEXTURE_2D, this.tex.u_heights);
    this.unpackRaw();
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, m.width, m.height, 0, gl.RED, gl.FLOAT, m.heights);
    this.params2d(true, true);
    this.hasLayers = false;
    this.fourier = null;
  }

  setLayers(bitmap0, bitmap1) {
    this.uploadImage('u_layer0', bitmap0);
    this.uploadImage('u_layer1', bitmap1);
    this.hasLayers = true;
  }

  /** Fourier layers (fourier_2 may be null) with the bake's `fourier_terms` and `fourier_range`. */
  setFourier(b0, b1, b2, terms, range) {
    this.uploadImage('u_four0', b0);
    this.uploadImage('u_four1', b1);
    if (b2) this.uploadImage('u_four2', b2);
    this.fourier = { terms, range };
  }

  /**
   * Output size in pixels of a view: native, or with `size` the longer side scaled to it and
   * the shorter rounded (preview::output_size), times 2×2 when tiled.
   */
  outputSize(opts) {
    const m = this.map;
    const k = opts.tiled ? 2 : 1;
    if (!opts.size) return [m.width * k, m.height * k];
    const long = Math.max(m.width, m.height);
    const w = Math.max(1, Math.round((m.width * opts.size) / long));
    const h = Math.max(1, Math.round((m.height * opts.size) / long));
    return [w * k, h * k];
  }

  /**
   * Draws into the bound framebuffer. opts: {light: [x,y,z] unit, hardness, shading
   * ('horizon'|'fourier'|'none'), mode ('shaded'|'layer'|'channel'|'normals'|'cube'|'heights'),
   * layer, channel, tiled, view: [x,y,z], fade}.
   */
  drawTo(width, height, opts) {
    const gl = this.gl;
    const m = this.map;
    const L = this.loc;
    gl.viewport(0, 0, width, height);
    gl.useProgram(this.program);
    gl.bindVertexArray(this.vao);
    for (const [name, unit] of Object.entries(this.units)) {
      if (L[name]) gl.uniform1i(L[name], unit);
    }
    const light = opts.light;
    const view = opts.view || fromAngles(DEFAULTS.viewAzimuth, DEFAULTS.viewElevation);
    const half = normalize([light[0] + view[0], light[1] + view[1], light[2] + view[2]]);
    const hl = Math.hypot(light[0], light[1]);
    const cs = hl > 0 ? [light[0] / hl, light[1] / hl] : [1, 0];
    const k = opts.tiled ? 2 : 1;
    const set = (name, fn, ...v) => {
      if (L[name]) gl[fn](L[name], ...v);
    };
    set('u_size', 'uniform2i', m.width, m.height);
    set('u_scale', 'uniform2f', (m.width * k) / width, (m.height * k) / height);
    set('u_out', 'uniform2f', width, height);
    set('u_wrap', 'uniform1i', m.wrap ? 1 : 0);
    set('u_rowStep', 'uniform1i', m.yAxis === 'down' ? 1 : -1);
    set('u_sqrt', 'uniform1i', m.encoding === 'sqrt' ? 1 : 0);
    set('u_mode', 'uniform1i', MODES[opts.mode || 'shaded'] ?? 0);
    set('u_shading', 'uniform1i', SHADINGS[opts.shading || 'horizon'] ?? 0);
    set('u_layerIndex', 'uniform1i', opts.layer || 0);
    set('u_channel', 'uniform1i', opts.channel || 0);
    const f = this.fourier || { terms: 5, range: 'standard' };
    set('u_terms', 'uniform1i', f.terms);
    set('u_fourierExpanded', 'uniform1i', f.range === 'expanded' ? 1 : 0);
    set('u_light', 'uniform3f', light[0], light[1], light[2]);
    set('u_half', 'uniform3f', half[0], half[1], half[2]);
    set('u_view', 'uniform3f', view[0], view[1], view[2]);
    set('u_lightXY', 'uniform2f', cs[0], cs[1]);
    set('u_hardness', 'uniform1f', opts.hardness ?? DEFAULTS.hardness);
    set('u_fade', 'uniform1f', opts.fade ?? DEFAULTS.horizonOcclusion);
    set('u_hrange', 'uniform2f', m.hmin, m.hmax);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  /** Draws into the canvas (resized to the view's output size). */
  draw(opts) {
    if (!this.map) return;
    const [w, h] = this.outputSize(opts);
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.drawTo(w, h, opts);
  }

  /** RGBA bytes of the bound framebuffer, rows from the top (GL reads bottom-up). */
  readRows(w, h) {
    const gl = this.gl;
    const raw = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, raw);
    const out = new Uint8Array(w * h * 4);
    for (let y = 0; y < h; y++) {
      out.set(raw.subarray((h - 1 - y) * w * 4, (h - y) * w * 4), y * w * 4);
    }
    return out;
  }

  /** The canvas's current pixels, rows from the top. */
  readCanvas() {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return { width: this.canvas.width, height: this.canvas.height,
      rgba: this.readRows(this.canvas.width, this.canvas.height) };
  }

  /** Renders `opts` off screen at the view's native output size and returns its pixels. */
  renderPixels(opts) {
    const gl = this.gl;
    const [w, h] = this.outputSize(opts);
    if (!this.fbo || this.fbo.w !== w || this.fbo.h !== h) {
      if (this.fbo) {
        gl.deleteFramebuffer(this.fbo.fb);
        gl.deleteRenderbuffer(this.fbo.rb);
      }
      const rb = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, rb);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.RGBA8, w, h);
      const fb = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, rb);
      this.fbo = { fb, rb, w, h };
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo.fb);
    this.drawTo(w, h, opts);
    const rgba = this.readRows(w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return { width: w, height: h, rgba };
  }
}
