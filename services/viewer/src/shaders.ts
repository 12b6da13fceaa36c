/**
 * GLSL ES 3.00 shaders. One point vertex shader serves three passes, chosen by a #define:
 * PASS_COLOR (plain splats: colour + linear depth), PASS_DEPTH (high-quality depth pre-pass,
 * pushed back by the splat radius) and PASS_ACCUM (weighted additive blend).
 *
 * Splat sizing per the seed: a point sampled by the scanner at depth Z_s with focal length F_s
 * covers the world size s = Z_s / F_s (the tiles' `size` attribute); seen by the virtual camera
 * at view depth Z_v with focal length F_v pixels it covers H_v = s * F_v / Z_v pixels, i.e.
 * H_v = (F_v / F_s) * (Z_s / Z_v).
 */

/** Fragment outputs of each pass, shared by the point and mesh fragment shaders (the render
 * targets the renderer binds for PASS_COLOR, PASS_DEPTH and PASS_ACCUM). */
const PASS_OUTPUTS = `#ifdef PASS_COLOR
layout(location = 0) out vec4 oColor;
layout(location = 1) out float oDepth;
#endif
#ifdef PASS_DEPTH
layout(location = 0) out float oDepth;
#endif
#ifdef PASS_ACCUM
layout(location = 0) out vec4 oAccum;
#endif
`;

export const POINT_VS = `
layout(location = 0) in vec3 aPosition;
layout(location = 1) in vec3 aColor;
layout(location = 2) in float aSize;
layout(location = 3) in vec3 aNormal;

uniform mat4 uModelView;
uniform mat4 uProjection;
uniform float uFocalPx;     // F_v: viewport focal length in pixels
uniform int uSizing;        // 0: seed (per-point world size / view depth), 1: fixed pixels
uniform float uFixedPx;
uniform float uSplatScale;  // splat diameter in units of the sample size
uniform float uFill;        // world size standing in for undrawn finer nodes (0 when none)
uniform float uMaxPx;
uniform float uBlendDepth;  // depth pre-pass offset, in splat radii
uniform int uGrazing;       // 1: widen splats of surfaces the scanner saw at a grazing angle
uniform vec3 uScanner;      // scanner position in the local frame

out vec3 vColor;
out float vDepth;
out float vSizePx;

void main() {
  vec4 viewPos = uModelView * vec4(aPosition, 1.0);
  float zv = max(-viewPos.z, 1e-9);
  float px;
  if (uSizing == 0) {
    float world = aSize;
    if (uGrazing == 1 && dot(aNormal, aNormal) > 0.5) {
      // The scanner's samples lie size / cos(incidence) apart along a tilted surface; the seed's
      // size holds across the ray only. Cap the stretch so silhouette samples stay bounded.
      float cosInc = abs(dot(normalize(aNormal), normalize(uScanner - aPosition)));
      world /= max(cosInc, 0.35);
    }
    world = max(world, uFill);
    px = uSplatScale * world * uFocalPx / zv;
  } else {
    px = uFixedPx;
  }
  px = clamp(px, 1.0, uMaxPx);
  gl_PointSize = px;
  vSizePx = px;
  vColor = aColor;
  vDepth = zv;
#ifdef PASS_DEPTH
  // Push the depth back by the splat's world radius so that splats of the same surface pass the
  // accumulation pass's depth test and blend, while surfaces further behind stay hidden.
  float radiusWorld = 0.5 * px * zv / uFocalPx;
  viewPos.z -= uBlendDepth * radiusWorld;
#endif
  gl_Position = uProjection * viewPos;
}
`;

export const POINT_FS = `
precision highp float;
in vec3 vColor;
in float vDepth;
in float vSizePx;
${PASS_OUTPUTS}
void main() {
  vec2 c = gl_PointCoord * 2.0 - 1.0;
  // Round splats. The test is in pixels and never removes a splat's only pixel: a 1-px point's
  // pixel centre can lie anywhere in its square (up to 0.71 px from the point's centre).
  float rPx = 0.5 * vSizePx * length(c);
  if (rPx > max(0.5 * vSizePx, 0.7072)) discard;
  float r2 = min(dot(c, c), 1.0);
#ifdef PASS_COLOR
  oColor = vec4(vColor, 1.0);
  oDepth = vDepth;
#endif
#ifdef PASS_DEPTH
  oDepth = vDepth;
#endif
#ifdef PASS_ACCUM
  // Weight falls off towards the splat's rim; c = sum(w_i c_i) / sum(w_i) in the composite pass.
  float w = 1.0 - 0.9 * r2;
  oAccum = vec4(vColor * w, w);
#endif
}
`;

export const QUAD_VS = `
void main() {
  // One triangle covering the viewport.
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
`;

export const COMPOSITE_FS = `
precision highp float;
uniform sampler2D uColor;
uniform sampler2D uAccum;
uniform sampler2D uDepth;
uniform int uHQ;
uniform int uEDL;
uniform float uEdlStrength;
uniform float uEdlRadius;
uniform vec3 uBackground;
out vec4 oColor;

void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec4 c;
  if (uHQ == 1) {
    vec4 a = texelFetch(uAccum, p, 0);
    c = a.a > 0.0 ? vec4(a.rgb / a.a, 1.0) : vec4(0.0);
  } else {
    c = texelFetch(uColor, p, 0);
  }
  if (c.a == 0.0) {
    oColor = vec4(uBackground, 1.0);
    return;
  }
  if (uEDL == 1) {
    // Eye-dome lighting: darken a pixel by how far it lies behind its 8 neighbours (log depth).
    float d = texelFetch(uDepth, p, 0).r;
    float ld = log2(max(d, 1e-12));
    float sum = 0.0;
    ivec2 size = textureSize(uDepth, 0);
    for (int i = 0; i < 8; i++) {
      float a = float(i) * 0.78539816;
      ivec2 q = clamp(p + ivec2(round(vec2(cos(a), sin(a)) * uEdlRadius)), ivec2(0), size - 1);
      float dn = texelFetch(uDepth, q, 0).r;
      if (dn > 0.0) sum += max(0.0, ld - log2(dn));
    }
    float shade = exp(-sum / 8.0 * 300.0 * uEdlStrength);
    c.rgb *= shade;
  }
  oColor = vec4(c.rgb, 1.0);
}
`;

/**
 * Mesh shaders (same passes as the points, chosen by the same #defines): a headlight Lambert
 * term |N · V| (two-sided, so open Poisson borders and inverted normals still light) times the
 * vertex colour, and the linear view depth for eye-dome lighting. Without NORMAL the face normal
 * comes from the screen-space derivatives of the view position (flat shading).
 */
export const MESH_VS = `
layout(location = 0) in vec3 aPosition;
layout(location = 1) in vec4 aColor;
layout(location = 2) in vec3 aNormal;
layout(location = 3) in vec2 aUv;
uniform mat4 uModelView;
uniform mat4 uProjection;
uniform mat3 uNormalMatrix;
out vec3 vViewPos;
out vec3 vNormal;
out vec3 vColor;
out vec2 vUv;
void main() {
  vUv = aUv;
  vec4 viewPos = uModelView * vec4(aPosition, 1.0);
  vViewPos = viewPos.xyz;
  vNormal = uNormalMatrix * aNormal;
  vColor = aColor.rgb;
  gl_Position = uProjection * viewPos;
}
`;

export const MESH_FS = `
precision highp float;
in vec3 vViewPos;
in vec3 vNormal;
in vec3 vColor;
in vec2 vUv;
uniform int uHasNormal;
uniform sampler2D uBaseMap;
uniform sampler2D uNormalMap;
uniform sampler2D uOcclusionMap;
uniform int uHasBaseMap;
uniform int uHasNormalMap;
uniform int uHasOcclusionMap;
${PASS_OUTPUTS}
void main() {
  vec3 n = uHasNormal == 1 ? vNormal : cross(dFdx(vViewPos), dFdy(vViewPos));
  float len = length(n);
  vec3 toEye = normalize(-vViewPos);
  if (len > 0.0 && uHasNormalMap == 1) {
    // Tangent-space normal map with a per-pixel cotangent frame (screen-space derivatives of
    // position and UV): the derivatives store no tangents. glTF's v runs down the image.
    vec3 nn = n / len;
    if (dot(nn, toEye) < 0.0) nn = -nn;
    vec3 dp1 = dFdx(vViewPos), dp2 = dFdy(vViewPos);
    vec2 du1 = dFdx(vUv), du2 = dFdy(vUv);
    vec3 dp2perp = cross(dp2, nn), dp1perp = cross(nn, dp1);
    vec3 t = dp2perp * du1.x + dp1perp * du2.x;
    vec3 b = dp2perp * du1.y + dp1perp * du2.y;
    float inv = inversesqrt(max(max(dot(t, t), dot(b, b)), 1e-30));
    vec3 tn = texture(uNormalMap, vUv).xyz * 2.0 - 1.0;
    vec3 m = t * inv * tn.x - b * inv * tn.y + nn * tn.z;
    if (length(m) > 0.0) { n = m; len = length(m); }
  }
  float lambert = len > 0.0 ? abs(dot(n / len, toEye)) : 1.0;
  vec3 base = uHasBaseMap == 1 ? texture(uBaseMap, vUv).rgb : vColor;
  float ao = uHasOcclusionMap == 1 ? texture(uOcclusionMap, vUv).r : 1.0;
  vec3 c = base * (0.25 * ao + 0.75 * lambert * mix(1.0, ao, 0.5));
#ifdef PASS_COLOR
  oColor = vec4(c, 1.0);
  oDepth = -vViewPos.z;
#endif
#ifdef PASS_DEPTH
  oDepth = -vViewPos.z;
#endif
#ifdef PASS_ACCUM
  oAccum = vec4(c, 1.0);
#endif
}
`;
