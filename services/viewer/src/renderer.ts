/**
 * WebGL2 point renderer.
 *
 * Standard mode: round splats into an offscreen colour + linear-depth target, then a composite
 * pass (background, optional eye-dome lighting) onto the canvas. High-quality mode: a depth
 * pre-pass with splats pushed back by their radius, an additive weighted pass of colour * w and
 * w into a half-float target, and the composite pass normalises c = sum(w_i c_i) / sum(w_i).
 *
 * Meshes (binary glTF, `gltf.ts`) draw into the same targets and depth buffer as the points, so
 * points and mesh hide each other correctly and eye-dome lighting applies to both; in high
 * quality mode the mesh writes the depth pre-pass and adds weight 1 per pixel in the blend.
 */

import { mat3, mat4 } from "gl-matrix";
import type { GlbMesh, MeshDraw } from "./gltf";
import type { DecodedPoints } from "./potree";
import { COMPOSITE_FS, MESH_FS, MESH_VS, POINT_FS, POINT_VS, QUAD_VS } from "./shaders";

export interface GpuNode {
  vao: WebGLVertexArrayObject;
  buffers: WebGLBuffer[];
  count: number;
}

/** A mesh on the GPU: one vertex buffer and one index buffer shared by all its draws. */
export interface GpuMesh {
  vertexBuffer: WebGLBuffer;
  indexBuffer: WebGLBuffer | null;
  draws: { vao: WebGLVertexArrayObject; draw: MeshDraw }[];
  triangles: number;
  bytes: number;
  /** Base colour, normal and occlusion maps (texture units MAP_UNIT + 0, 1, 2), null where absent. */
  maps: (WebGLTexture | null)[];
}

/** First texture unit of the mesh maps (the point and EDL passes use the units below). */
const MAP_UNIT = 4;

export interface DrawItem {
  gpu: GpuNode;
  /** World size standing in for finer nodes not drawn (0 when the node is fully refined). */
  fill: number;
}

export interface FrameSettings {
  modelView: Float32Array;
  projection: Float32Array;
  focalPx: number;
  sizing: "seed" | "fixed";
  fixedPx: number;
  splatScale: number;
  edl: boolean;
  edlStrength: number;
  edlRadius: number;
  hq: boolean;
  blendDepth: number;
  background: [number, number, number];
  grazing: boolean;
  /** Scanner position in the local frame (for the grazing-angle correction). */
  scanner: [number, number, number];
  /** World-to-view matrix (float64, column-major) for meshes, which are in world coordinates. */
  view?: ArrayLike<number>;
}

function compile(gl: WebGL2RenderingContext, type: number, source: string): WebGLShader {
  const shader = gl.createShader(type)!;
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    throw new Error(`shader compile failed: ${gl.getShaderInfoLog(shader)}`);
  }
  return shader;
}

function link(gl: WebGL2RenderingContext, vs: string, fs: string, defines: string[] = []): WebGLProgram {
  const head = "#version 300 es\nprecision highp float;\nprecision highp int;\n" + defines.map((d) => `#define ${d}\n`).join("");
  const program = gl.createProgram()!;
  gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, head + vs));
  gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, head + fs));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
    throw new Error(`shader link failed: ${gl.getProgramInfoLog(program)}`);
  }
  return program;
}

class Program {
  readonly program: WebGLProgram;
  private locations = new Map<string, WebGLUniformLocation | null>();
  constructor(
    private gl: WebGL2RenderingContext,
    vs: string,
    fs: string,
    defines: string[] = [],
  ) {
    this.program = link(gl, vs, fs, defines);
  }
  loc(name: string): WebGLUniformLocation | null {
    if (!this.locations.has(name)) this.locations.set(name, this.gl.getUniformLocation(this.program, name));
    return this.locations.get(name)!;
  }
}

export class Renderer {
  readonly gl: WebGL2RenderingContext;
  readonly maxPointPx: number;
  private colorPass: Program;
  private depthPass: Program;
  private accumPass: Program;
  private composite: Program;
  private width = 0;
  private height = 0;
  private colorTex: WebGLTexture | null = null;
  private depthLinTex: WebGLTexture | null = null;
  private accumTex: WebGLTexture | null = null;
  private depthTex: WebGLTexture | null = null;
  private fboColor: WebGLFramebuffer | null = null;
  private fboDepth: WebGLFramebuffer | null = null;
  private fboAccum: WebGLFramebuffer | null = null;
  private emptyVao: WebGLVertexArrayObject;
  private meshColor: Program;
  private meshDepth: Program;
  private meshAccum: Program;

  constructor(readonly canvas: HTMLCanvasElement) {
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, preserveDrawingBuffer: false });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    if (!gl.getExtension("EXT_color_buffer_float")) {
      throw new Error("WebGL2 lacks EXT_color_buffer_float (needed for depth and blend targets)");
    }
    this.gl = gl;
    this.maxPointPx = (gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE) as Float32Array)[1];
    this.colorPass = new Program(gl, POINT_VS, POINT_FS, ["PASS_COLOR"]);
    this.depthPass = new Program(gl, POINT_VS, POINT_FS, ["PASS_DEPTH"]);
    this.accumPass = new Program(gl, POINT_VS, POINT_FS, ["PASS_ACCUM"]);
    this.composite = new Program(gl, QUAD_VS, COMPOSITE_FS);
    this.meshColor = new Program(gl, MESH_VS, MESH_FS, ["PASS_COLOR"]);
    this.meshDepth = new Program(gl, MESH_VS, MESH_FS, ["PASS_DEPTH"]);
    this.meshAccum = new Program(gl, MESH_VS, MESH_FS, ["PASS_ACCUM"]);
    this.emptyVao = gl.createVertexArray()!;
  }

  private texture(internal: number, format: number, type: number): WebGLTexture {
    const gl = this.gl;
    const tex = gl.createTexture()!;
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, this.width, this.height, 0, format, type, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return tex;
  }

  private framebuffer(colors: WebGLTexture[]): WebGLFramebuffer {
    const gl = this.gl;
    const fbo = gl.createFramebuffer()!;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    colors.forEach((tex, i) => gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, tex, 0));
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.TEXTURE_2D, this.depthTex, 0);
    gl.drawBuffers(colors.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`framebuffer incomplete (0x${status.toString(16)})`);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return fbo;
  }

  /** Size the drawing buffer and offscreen targets in device pixels. */
  resize(width: number, height: number): void {
    if (width === this.width && height === this.height) return;
    const gl = this.gl;
    this.canvas.width = width;
    this.canvas.height = height;
    this.width = width;
    this.height = height;
    for (const t of [this.colorTex, this.depthLinTex, this.accumTex, this.depthTex]) if (t) gl.deleteTexture(t);
    for (const f of [this.fboColor, this.fboDepth, this.fboAccum]) if (f) gl.deleteFramebuffer(f);
    this.colorTex = this.texture(gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE);
    this.depthLinTex = this.texture(gl.R32F, gl.RED, gl.FLOAT);
    this.accumTex = this.texture(gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT);
    this.depthTex = this.texture(gl.DEPTH_COMPONENT32F, gl.DEPTH_COMPONENT, gl.FLOAT);
    this.fboColor = this.framebuffer([this.colorTex, this.depthLinTex]);
    this.fboDepth = this.framebuffer([this.depthLinTex]);
    this.fboAccum = this.framebuffer([this.accumTex]);
  }

  upload(points: DecodedPoints): GpuNode {
    const gl = this.gl;
    const vao = gl.createVertexArray()!;
    gl.bindVertexArray(vao);
    const buffers: WebGLBuffer[] = [];
    const attribute = (loc: number, data: ArrayBufferView, size: number, type: number, normalized: boolean) => {
      const buf = gl.createBuffer()!;
      gl.bindBuffer(gl.ARRAY_BUFFER, buf);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, type, normalized, 0, 0);
      buffers.push(buf);
    };
    attribute(0, points.positions, 3, gl.FLOAT, false);
    if (points.colors) attribute(1, points.colors, 3, gl.UNSIGNED_BYTE, true);
    if (points.sizes) attribute(2, points.sizes, 1, gl.FLOAT, false);
    if (points.normals) attribute(3, points.normals, 3, gl.FLOAT, false);
    gl.bindVertexArray(null);
    return { vao, buffers, count: points.count };
  }

  /**
   * Upload a parsed GLB: its vertex byte range in one ARRAY_BUFFER and its index range in one
   * ELEMENT_ARRAY_BUFFER (32-bit indices as stored), one vertex array object per draw.
   * Throws when the GPU refuses the buffers (out of memory).
   */
  uploadMesh(mesh: GlbMesh): GpuMesh {
    const gl = this.gl;
    while (gl.getError() !== gl.NO_ERROR); // start from a clean error state
    const vertexBuffer = gl.createBuffer()!;
    gl.bindBuffer(gl.ARRAY_BUFFER, vertexBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, mesh.vertexBytes, gl.STATIC_DRAW);
    let indexBuffer: WebGLBuffer | null = null;
    const draws: GpuMesh["draws"] = [];
    for (const draw of mesh.draws) {
      const vao = gl.createVertexArray()!;
      gl.bindVertexArray(vao);
      gl.bindBuffer(gl.ARRAY_BUFFER, vertexBuffer);
      for (const a of draw.attributes) {
        gl.enableVertexAttribArray(a.location);
        gl.vertexAttribPointer(a.location, a.size, a.type, a.normalized, a.stride, a.offset);
      }
      if (draw.indexType !== null) {
        if (!indexBuffer) {
          // Element buffers must be bound inside a VAO before their data goes in.
          indexBuffer = gl.createBuffer()!;
          gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, indexBuffer);
          gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, mesh.indexBytes, gl.STATIC_DRAW);
        } else {
          gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, indexBuffer);
        }
      }
      draws.push({ vao, draw });
    }
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    const maps = [mesh.maps?.base, mesh.maps?.normal, mesh.maps?.occlusion].map((img) => {
      if (!img) return null;
      const tex = gl.createTexture()!;
      gl.activeTexture(gl.TEXTURE0 + MAP_UNIT);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      // glTF's UV origin is the image's top-left: rows go up as stored (no flip).
      gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, img);
      gl.generateMipmap(gl.TEXTURE_2D);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      return tex;
    });
    gl.bindTexture(gl.TEXTURE_2D, null);
    gl.activeTexture(gl.TEXTURE0);
    const mapBytes = [mesh.maps?.base, mesh.maps?.normal, mesh.maps?.occlusion].reduce(
      (sum, img) => sum + (img ? ((img as { width: number }).width * (img as { height: number }).height * 16) / 3 : 0),
      0,
    );
    const gpu: GpuMesh = {
      vertexBuffer,
      indexBuffer,
      draws,
      triangles: mesh.triangles,
      bytes: mesh.vertexBytes.byteLength + mesh.indexBytes.byteLength + mapBytes,
      maps,
    };
    const error = gl.getError();
    if (error !== gl.NO_ERROR) {
      this.releaseMesh(gpu);
      throw new Error(`the GPU refused the mesh buffers (${(gpu.bytes / 1e6).toFixed(0)} MB, GL error 0x${error.toString(16)})`);
    }
    return gpu;
  }

  releaseMesh(mesh: GpuMesh): void {
    const gl = this.gl;
    for (const d of mesh.draws) gl.deleteVertexArray(d.vao);
    gl.deleteBuffer(mesh.vertexBuffer);
    if (mesh.indexBuffer) gl.deleteBuffer(mesh.indexBuffer);
    for (const t of mesh.maps) if (t) gl.deleteTexture(t);
  }

  private drawMeshes(program: Program, meshes: GpuMesh[], s: FrameSettings): void {
    if (!meshes.length || !s.view) return;
    const gl = this.gl;
    gl.useProgram(program.program);
    gl.uniformMatrix4fv(program.loc("uProjection"), false, s.projection);
    // Constant attributes where a primitive lacks colour or normal (not part of VAO state).
    gl.vertexAttrib4f(1, 0.8, 0.8, 0.8, 1);
    gl.vertexAttrib3f(2, 0, 0, 1);
    const modelView = mat4.create();
    const normal = mat3.create();
    for (const mesh of meshes) {
      ["uBaseMap", "uNormalMap", "uOcclusionMap"].forEach((name, k) => {
        gl.activeTexture(gl.TEXTURE0 + MAP_UNIT + k);
        gl.bindTexture(gl.TEXTURE_2D, mesh.maps[k]);
        gl.uniform1i(program.loc(name), MAP_UNIT + k);
      });
      gl.activeTexture(gl.TEXTURE0);
      gl.uniform1i(program.loc("uHasBaseMap"), mesh.maps[0] ? 1 : 0);
      gl.uniform1i(program.loc("uHasNormalMap"), mesh.maps[1] ? 1 : 0);
      gl.uniform1i(program.loc("uHasOcclusionMap"), mesh.maps[2] ? 1 : 0);
      for (const { vao, draw } of mesh.draws) {
        // view * node in float64, rounded to float32 once.
        mat4.multiply(modelView, s.view as mat4, draw.matrix as unknown as mat4);
        mat3.normalFromMat4(normal, modelView);
        gl.uniformMatrix4fv(program.loc("uModelView"), false, new Float32Array(modelView));
        gl.uniformMatrix3fv(program.loc("uNormalMatrix"), false, new Float32Array(normal));
        gl.uniform1i(program.loc("uHasNormal"), draw.hasNormal ? 1 : 0);
        gl.bindVertexArray(vao);
        if (draw.indexType !== null) gl.drawElements(draw.mode, draw.count, draw.indexType, draw.indexOffset);
        else gl.drawArrays(draw.mode, 0, draw.count);
      }
    }
    gl.bindVertexArray(null);
  }

  release(node: GpuNode): void {
    const gl = this.gl;
    gl.deleteVertexArray(node.vao);
    for (const b of node.buffers) gl.deleteBuffer(b);
  }

  private drawPoints(program: Program, items: DrawItem[], s: FrameSettings): void {
    const gl = this.gl;
    gl.useProgram(program.program);
    gl.uniformMatrix4fv(program.loc("uModelView"), false, s.modelView);
    gl.uniformMatrix4fv(program.loc("uProjection"), false, s.projection);
    gl.uniform1f(program.loc("uFocalPx"), s.focalPx);
    gl.uniform1i(program.loc("uSizing"), s.sizing === "seed" ? 0 : 1);
    gl.uniform1f(program.loc("uFixedPx"), s.fixedPx);
    gl.uniform1f(program.loc("uSplatScale"), s.splatScale);
    gl.uniform1f(program.loc("uMaxPx"), this.maxPointPx);
    gl.uniform1f(program.loc("uBlendDepth"), s.blendDepth);
    // Constant attribute values for tiles without colour or size (not part of VAO state).
    gl.vertexAttrib3f(1, 0.8, 0.8, 0.8);
    gl.vertexAttrib1f(2, 0);
    gl.vertexAttrib3f(3, 0, 0, 0);
    gl.uniform1i(program.loc("uGrazing"), s.grazing ? 1 : 0);
    gl.uniform3f(program.loc("uScanner"), ...s.scanner);
    const fillLoc = program.loc("uFill");
    for (const item of items) {
      if (item.gpu.count === 0) continue;
      gl.uniform1f(fillLoc, item.fill);
      gl.bindVertexArray(item.gpu.vao);
      gl.drawArrays(gl.POINTS, 0, item.gpu.count);
    }
    gl.bindVertexArray(null);
  }

  render(items: DrawItem[], s: FrameSettings, meshes: GpuMesh[] = []): void {
    const gl = this.gl;
    gl.viewport(0, 0, this.width, this.height);
    gl.disable(gl.BLEND);
    gl.enable(gl.DEPTH_TEST);
    gl.depthMask(true);
    if (s.hq) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fboDepth);
      gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]);
      gl.clearBufferfv(gl.DEPTH, 0, [1]);
      gl.depthFunc(gl.LESS);
      this.drawPoints(this.depthPass, items, s);
      this.drawMeshes(this.meshDepth, meshes, s);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fboAccum);
      gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]);
      gl.depthFunc(gl.LEQUAL);
      gl.depthMask(false);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.ONE, gl.ONE);
      this.drawPoints(this.accumPass, items, s);
      this.drawMeshes(this.meshAccum, meshes, s);
      gl.disable(gl.BLEND);
      gl.depthMask(true);
    } else {
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fboColor);
      gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]);
      gl.clearBufferfv(gl.COLOR, 1, [0, 0, 0, 0]);
      gl.clearBufferfv(gl.DEPTH, 0, [1]);
      gl.depthFunc(gl.LESS);
      this.drawPoints(this.colorPass, items, s);
      this.drawMeshes(this.meshColor, meshes, s);
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.disable(gl.DEPTH_TEST);
    const c = this.composite;
    gl.useProgram(c.program);
    const bind = (unit: number, tex: WebGLTexture | null, name: string) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.uniform1i(c.loc(name), unit);
    };
    bind(0, this.colorTex, "uColor");
    bind(1, this.accumTex, "uAccum");
    bind(2, this.depthLinTex, "uDepth");
    gl.uniform1i(c.loc("uHQ"), s.hq ? 1 : 0);
    gl.uniform1i(c.loc("uEDL"), s.edl ? 1 : 0);
    gl.uniform1f(c.loc("uEdlStrength"), s.edlStrength);
    gl.uniform1f(c.loc("uEdlRadius"), s.edlRadius);
    gl.uniform3f(c.loc("uBackground"), ...s.background);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
    for (let unit = 0; unit < 3; unit++) {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, null);
    }
  }
}
