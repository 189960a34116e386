#version 330 core
#if SHADE && N_LIGHTS > 0
// findLSB, to walk the lights to look up and shade as bit masks. Only where those loops
// are: with the extension on, llvmpipe ran the farm's pass (no LocalLight) ~6 % slower.
#extension GL_ARB_gpu_shader5 : require
#endif
// Compiled per pass shape (light_pass.LightPass._program_for) with these defines
// in front of this file, because llvmpipe runs every branch of the code under masks
// (only loops end early): code for absent lights, maps or outputs would cost as much
// as used code.
//   N_LIGHTS     LocalLight slots of this pass's tile lists, 0..16
//   TILED        1: each tile of points has its own lights (light_table, tile_slots);
//                0: every point the pass's (uniform arrays: fewer fetches, for a stage
//                whose lights all fit one pass, and the codes' lookup)
//   N_DISTANT    DistantLights in this pass (with SHADE, first pass only), 0..2
//   HAS_DYNAMIC  1 when the scene has animated casters (a second cube per light)
//   COAT         1 when a point of the pass has a clear coat (with SHADE)
//   TERMINATOR   1 when a point of the pass moves onto a smooth mesh's surface for its
//                shadow tests (the terminator textures; TERMINATOR_FADE, model/surface.py)
//   AREA         1 when a LocalLight is a Rect or Disk light (with SHADE): its pairs are
//                shaded with its area factor (area_factor); LIGHT_TEXELS the light
//                table's texels a light (3, 6 with AREA); DISK_CORNERS, DISK_SCALE a
//                disk's outline (area_light_kernels.DISK_CORNERS, DISK_CORNER_SCALE)
//   LUT_ROWS, LUT_COSINES  the albedo table's rows and n.v columns
//                (preview_surface.specular_albedo_table: a last column of means follows)
//   SHADE        1 to also shade the lit pairs (the direct output)
//   CUBE_SIZE    texels per cube face side (shadow_maps.CUBE_MAP_SIZE)
//   TAN_HALF     tangent of a cube face's half field of view (its guard band)
//   LINE_W, LINE_H, PAGE_W, PAGE_H  (columns, rows) of the cube buffer's tiles, unsigned
//                (light_pass.CUBE_LINE_TILE, CUBE_PAGE_TILE)
// (constants rather than uniforms: the expressions of them fold at compile time instead
// of running per fragment)
// LocalLight shadow lookups, fragment stage: one fragment per query point, up to 16
// lights per pass, packed as one byte each into one RGBA32UI attachment (light j in
// channel j / 4, bits 8 (j % 4) .. 8 (j % 4) + 7: little-endian bytes in light order).
// The same test as shadow_maps.cube_visibility (see there and CubeMap for the cube
// layout); keep the two in step.
//
// Inputs (textures, texelFetch only):
//   points  : RGB32F, (x, y, z) origin-relative world metres of point k at texel
//             (k % width, k / width)
//   normals : RGB32F, (x, y, z) unit shading normal facing the viewer, same layout
//   cubes   : RG32F buffer texture, (min, max) caster forward distance over the texel
//             neighbourhood; face f of a cube whose first face is F at
//             (F + f) * CUBE_SIZE², its texels in tiles (light_pass._tiled, cube_test)
//   to_eye  : RGB32F, (x, y, z) unit direction from the point to the viewer, same layout
//   surface : RGBA32F, the point's UsdPreviewSurface row (model/preview_surface.py, 16
//             floats) as the four texels (4 (k % width) + i, k / width), i = 0..3
//   albedo_lut : RG32F, (A, B) of preview_surface.specular_albedo_table: texel (j, i) its
//             row i (roughness), column j (n.v; the last column the row's means)
//   terminator, lifts : RGB32F (with TERMINATOR), the point's face normal turned to its
//             shading normal's side and its move onto the smooth surface, metres, both 0
//             where it does not move (engine/terminator.py Terminator.normals, .lifts)
//   dmap_s<k>, dmap_d<k> : RG32F, (min, max) caster depth over the texel neighbourhood
//             of DistantLight k's static / animated orthographic map (as
//             shadow_maps.ShadowMap; the test of shadow_maps.filtered_visibility)
// Output code per light: 1 lit, 0 shadowed / out of range / facing away, 2 uncertain.
// A point of a smooth mesh is tested as its shadow rays leave it (engine/terminator.py):
// moved onto the smooth surface, the move faded out by n_g.l = TERMINATOR_FADE.
// Also the local shading of the lit pairs (shade_kernels.shade_kernel's model and its
// BRDF, shade_kernels.brdf_cos: keep in step, tests/engine/test_preview_surface.py):
//   direct    : rgb = sum over lit lights of radiance * window / d^2 (DistantLights:
//               radiance; a Rect or Disk light times its area factor) * brdf_cos, a =
//               bit j set where LocalLight j is uncertain, bit 16 + k where
//               DistantLight k is (exact in float up to 2^24)

uniform sampler2D points;
uniform sampler2D normals;
uniform samplerBuffer cubes;
uniform int n_points;
uniform int width;
#if TILED
// The LocalLights, three texels each (light_pass.LightPass._upload_lights): (position,
// origin-relative metres; range, metres, 0 = reaches nothing), (radiance, linear RGB;
// the cube faces' near plane, metres), (first face of the static casters' cube, of the
// animated casters' cube, -1 = none; 0; 0); with AREA three more, its shape (half axis
// u, kind; half axis v; axis: light_pass._area_texels).
uniform samplerBuffer light_table;
// Each tile's lights (a tile: up to light_pass.LOOKUP_TILE consecutive points; each
// point's in point_tiles, laid out as the points): the pass's slot j of tile t at texel
// (N_SLOTS (t % SLOT_TILES) + j, t / SLOT_TILES), a light of light_table, or -1 (the
// lights whose range reaches the tile's points, in increasing order: light_pass).
uniform isampler2D tile_slots;
uniform isampler2D point_tiles;
#else
// The pass's LocalLights (slot j: light j of these arrays), the same for every point.
uniform vec3 light_pos[16];     // origin-relative metres
uniform float light_range[16];  // metres; 0 = the light reaches nothing
uniform float light_near[16];   // the cube faces' near plane, metres
uniform int static_face[16];    // first face of the static casters' cube, -1 = none
uniform int dynamic_face[16];   // first face of the animated casters' cube, -1 = none
uniform vec3 light_radiance[16];     // linear RGB
#if AREA
uniform vec4 light_u[16];       // a Rect or Disk light's half axis u (metres), its kind
uniform vec3 light_v[16];       // its half axis v (metres)
uniform vec3 light_axis[16];    // the unit direction it emits along (its -Z)
#endif
#endif
uniform float bias_texels;      // SHADOW_BIAS_TEXELS
uniform float box_radius;       // SHADOW_REFINE_RADIUS + 0.5 (nearest-texel offset)
uniform float slope_clamp;      // 1 / SHADOW_MIN_COS
uniform sampler2D to_eye;
uniform float min_light_distance;    // shading.MIN_LIGHT_DISTANCE
uniform sampler2D surface;
uniform sampler2D albedo_lut;
uniform float min_roughness;         // preview_surface.MIN_ROUGHNESS
uniform float min_cosine;            // preview_surface.MIN_COSINE
#if TERMINATOR
uniform sampler2D terminator;
uniform sampler2D lifts;
#endif

#if N_DISTANT > 0
uniform vec3 distant_dir[N_DISTANT];       // unit, towards the light
uniform vec3 distant_radiance[N_DISTANT];  // linear RGB
// Per map m = 2 k (static) and 2 k + 1 (animated casters) of DistantLight k:
uniform vec3 map_x[2 * N_DISTANT];  // rows of the light frame (rel metres -> light)
uniform vec3 map_y[2 * N_DISTANT];
uniform vec3 map_z[2 * N_DISTANT];
uniform vec2 map_lo[2 * N_DISTANT];     // lower corner of the map, metres
uniform vec2 map_texel[2 * N_DISTANT];  // texel size, metres
uniform int map_size[2 * N_DISTANT];    // texels per side, 0 = no map (no casters)
uniform float slope_bias_texels;        // SHADOW_SLOPE_BIAS_TEXELS
uniform float min_cos;                  // SHADOW_MIN_COS
uniform sampler2D dmap_s0;
uniform sampler2D dmap_d0;
#endif
#if N_DISTANT > 1
uniform sampler2D dmap_s1;
uniform sampler2D dmap_d1;
#endif

layout(location = 0) out uvec4 codes;
layout(location = 1) out vec4 direct;

// One cube (first face ``first``, -1 = none): 1 lit, 0 shadowed, -1 uncertain. Only
// ``wanted`` pairs read their texel; the others (masked lanes, which llvmpipe runs all
// the same) read texel 0, which stays in cache: the cubes (12 MB a light) far exceed
// the caches, and such misses were ~10 % of the sewer's pass.
float cube_test(int first, int face, ivec2 texel_xy, float test, bool wanted)
{
    if (first < 0) {
        return 1.0;
    }
    // light_pass._tiled: pages (row-major), in them lines (row-major), in them texels
    // (row-major); unsigned, so that the power-of-two divisions compile to shifts.
    uint x = uint(texel_xy.x);
    uint y = uint(texel_xy.y);
    uint page = (y / PAGE_H) * (uint(CUBE_SIZE) / PAGE_W) + x / PAGE_W;
    uint line = (y % PAGE_H / LINE_H) * (PAGE_W / LINE_W) + x % PAGE_W / LINE_W;
    uint in_face = (page * (PAGE_H / LINE_H) * (PAGE_W / LINE_W) + line) * (LINE_W * LINE_H)
        + (y % LINE_H) * LINE_W + x % LINE_W;
    int at = wanted ? (first + face) * (CUBE_SIZE * CUBE_SIZE) + int(in_face) : 0;
    vec2 mm = texelFetch(cubes, at).rg;
    if (test <= mm.x) {
        return 1.0;
    }
    if (test > mm.y) {
        return 0.0;
    }
    return -1.0;
}

// Light li's texel c of light_table (untiled: the same from the uniforms; c is a
// constant at every call, so the choice folds away).
vec4 light_texel(int li, int c)
{
#if TILED
    return texelFetch(light_table, LIGHT_TEXELS * li + c);
#else
#if AREA
    if (c >= 3) {  // the shape (area_factor)
        return c == 3 ? light_u[li] : vec4(c == 4 ? light_v[li] : light_axis[li], 0.0);
    }
#endif
    return c == 0 ? vec4(light_pos[li], light_range[li])
        : (c == 1 ? vec4(light_radiance[li], light_near[li])
                  : vec4(float(static_face[li]), float(dynamic_face[li]), 0.0, 0.0));
#endif
}

// The share of a point's move ``lift`` its shadow test against a light takes: 1 where
// its face (normal ng) turns from the light (cos = ng.l times ``len``, l's length), 0
// from n_g.l = TERMINATOR_FADE on (trace_kernels.shadow_rays's fade).
vec3 terminator_move(vec3 lift, vec3 ng, float cos, float len)
{
    return clamp(1.0 - cos / max(TERMINATOR_FADE * len, 1e-30), 0.0, 1.0) * lift;
}

// Light li's shadow test at a point v (from the light to the point, d2 = |v|²) with
// normal n, face normal ng and move onto the smooth surface ``lift`` (both 0: none): 1
// lit, 0 shadowed / out of range / facing away, -1 uncertain.
float lookup(int li, vec3 v, float d2, vec3 n, vec3 ng, vec3 lift)
{
    float r = light_texel(li, 0).w;
    float ndv = dot(n, v);
    // Out of range or the light behind the surface: 0; nearer than the near plane: 1.
    // Selected at the end, not returned early, so that the fetches know (cube_test).
    bool reach = d2 < r * r && ndv < 0.0;
#if TERMINATOR
    for (int once = dot(ng, ng) > 0.0 ? 0 : 1; once < 1; ++once) {  // as main's fetch
        v += terminator_move(lift, ng, -dot(ng, v), sqrt(d2));
        ndv = dot(n, v);
    }
#endif
    vec3 a = abs(v);
    int axis;
    float w;
    float major;
    vec2 bc;
    vec2 nbc;
    if (a.x >= a.y && a.x >= a.z) {
        axis = 0; w = a.x; major = v.x; bc = v.yz; nbc = n.yz;
    } else if (a.y >= a.z) {
        axis = 1; w = a.y; major = v.y; bc = v.xz; nbc = n.xz;
    } else {
        axis = 2; w = a.z; major = v.z; bc = v.xy; nbc = n.xy;
    }
    bool beyond_near = w > light_texel(li, 1).w;
    bool wanted = reach && beyond_near;
    int face = 2 * axis + (major < 0.0 ? 1 : 0);
    float texel = w * (2.0 * TAN_HALF / float(CUBE_SIZE));  // texel width at w, metres
    float slope = min(texel * w * (abs(nbc.x) + abs(nbc.y)) / max(-ndv, 1e-30),
                      slope_clamp * texel);
    float test = w - texel * bias_texels - box_radius * slope;
    vec2 f = floor(bc * ((0.5 * float(CUBE_SIZE) / TAN_HALF) / w) + 0.5 * float(CUBE_SIZE));
    ivec2 t = clamp(ivec2(f), ivec2(0), ivec2(CUBE_SIZE - 1));
    vec4 faces = light_texel(li, 2);
    float vs = cube_test(int(faces.x), face, t, test, wanted);
#if HAS_DYNAMIC
    float vd = cube_test(int(faces.y), face, t, test, wanted);
    float vis = (vs == 0.0 || vd == 0.0) ? 0.0 : min(vs, vd);  // -1: either uncertain
#else
    float vis = vs;
#endif
    return reach ? (beyond_near ? vis : 1.0) : 0.0;
}

uint code(float r)
{
    return r > 0.5 ? 1u : (r < -0.5 ? 2u : 0u);
}

#if SHADE
const float PI = 3.14159265358979;

// A row of the albedo table at roughness r: its first node and the weight of the next
// (shade_kernels.lut_albedo's y0, fy), found once a point, not once a light.
struct LutRow {
    int y0;
    float fy;
};

LutRow lut_row(float r)
{
    float y = clamp(r, 0.0, 1.0) * float(LUT_ROWS - 1);
    int y0 = min(int(y), LUT_ROWS - 2);
    return LutRow(y0, y - float(y0));
}

// (A, B) of the albedo table on row ``row`` at cosine mu, bilinear between its nodes
// (shade_kernels.lut_albedo).
vec2 lut_albedo(LutRow row, float mu)
{
    float x = clamp(mu, 0.0, 1.0) * float(LUT_COSINES - 1);
    int x0 = min(int(x), LUT_COSINES - 2);
    float fx = x - float(x0);
    vec2 top = mix(texelFetch(albedo_lut, ivec2(x0, row.y0), 0).rg,
                   texelFetch(albedo_lut, ivec2(x0 + 1, row.y0), 0).rg, fx);
    vec2 bottom = mix(texelFetch(albedo_lut, ivec2(x0, row.y0 + 1), 0).rg,
                      texelFetch(albedo_lut, ivec2(x0 + 1, row.y0 + 1), 0).rg, fx);
    return mix(top, bottom, row.fy);
}

// The table's cosine-weighted means on row ``row`` (shade_kernels.lut_mean): the last
// column.
vec2 lut_mean(LutRow row)
{
    return mix(texelFetch(albedo_lut, ivec2(LUT_COSINES, row.y0), 0).rg,
               texelFetch(albedo_lut, ivec2(LUT_COSINES, row.y0 + 1), 0).rg, row.fy);
}

// GGX D times the height-correlated Smith V (shade_kernels.ggx_dv).
float ggx_dv(float alpha, float nl, float nv, float nh)
{
    float a2 = alpha * alpha;
    float d = nh * nh * (a2 - 1.0) + 1.0;
    float v = nl * sqrt(nv * nv * (1.0 - a2) + a2) + nv * sqrt(nl * nl * (1.0 - a2) + a2);
    return a2 / (PI * d * d) * 0.5 / max(v, 1e-30);
}

// A point's surface row (model/preview_surface.py columns) and what the BRDF reads of
// it whatever the light (shade_kernels.point_terms): the terms of the view direction
// are found once a point, each light then adds only its own.
struct Surface {
    vec3 f0;
    vec3 f90;
    float rough;       // at least min_roughness
    LutRow row;        // the albedo table's row at ``rough``
    // The diffuse lobe but for its light-side factor (1 - E(n.l)):
    // diffuse colour (1 - E(n.v)) / (1 - E_avg) (shade_kernels.brdf_cos).
    vec3 diffuse_v;
#if COAT
    float coat;
    float coat_rough;  // at least min_roughness
    float coat_f0;
    LutRow coat_row;
    float coat_t_v;    // what the clear coat lets through towards the eye
#endif
};

Surface surface_at(ivec2 xy, float nv)
{
    vec4 s0 = texelFetch(surface, ivec2(4 * xy.x, xy.y), 0);
    vec4 s1 = texelFetch(surface, ivec2(4 * xy.x + 1, xy.y), 0);
    vec4 s2 = texelFetch(surface, ivec2(4 * xy.x + 2, xy.y), 0);
    Surface s;
    s.f0 = vec3(s0.w, s1.xy);
    s.f90 = vec3(s1.zw, s2.x);
    s.rough = max(s2.y, min_roughness);
    s.row = lut_row(s.rough);
    vec2 ab_v = lut_albedo(s.row, nv);
    vec2 ab_mean = lut_mean(s.row);
    vec3 ev = min(s.f0 * ab_v.x + s.f90 * ab_v.y, vec3(1.0));
    vec3 mean = min(s.f0 * ab_mean.x + s.f90 * ab_mean.y, vec3(1.0));
    s.diffuse_v = s0.xyz * (1.0 - ev) / max(1.0 - mean, vec3(1e-4));
#if COAT
    vec4 s3 = texelFetch(surface, ivec2(4 * xy.x + 3, xy.y), 0);
    s.coat = s2.z;
    s.coat_rough = max(s2.w, min_roughness);
    s.coat_f0 = s3.x;
    s.coat_row = lut_row(s.coat_rough);
    vec2 coat_ab_v = lut_albedo(s.coat_row, nv);
    s.coat_t_v = 1.0 - s.coat * min(s.coat_f0 * coat_ab_v.x + coat_ab_v.y, 1.0);
#endif
    return s;
}

// pi f(l, v) n.l (RGB) of the point's UsdPreviewSurface BRDF (shade_kernels.brdf_cos):
// unit normal n, direction to the eye e (n.e = nv, clamped), to the light l.
vec3 brdf_cos(Surface s, vec3 n, vec3 e, vec3 l, float nv)
{
    float nl = dot(n, l);
    if (!(nl > 0.0)) {
        return vec3(0.0);
    }
    vec3 h = l + e;
    float len = length(h);
    h = len > 1e-12 ? h / len : n;
    float nh = max(dot(n, h), 0.0);
    float vh = clamp(dot(e, h), 0.0, 1.0);
    float m = 1.0 - vh;
    float m2 = m * m;
    float s5 = m2 * m2 * m;  // (1 - v.h)^5, Schlick's
    float dv = ggx_dv(s.rough * s.rough, nl, nv, nh);
    vec2 ab_l = lut_albedo(s.row, nl);
    vec3 el = min(s.f0 * ab_l.x + s.f90 * ab_l.y, vec3(1.0));
    vec3 diffuse = s.diffuse_v * (1.0 - el);
    vec3 spec = (s.f0 + (s.f90 - s.f0) * s5) * dv;
#if COAT
    float coat = 0.0;
    float t = 1.0;
    if (s.coat > 0.0) {
        coat = s.coat * (s.coat_f0 + (1.0 - s.coat_f0) * s5)
            * ggx_dv(s.coat_rough * s.coat_rough, nl, nv, nh);
        vec2 coat_l = lut_albedo(s.coat_row, nl);
        t = s.coat_t_v * (1.0 - s.coat * min(s.coat_f0 * coat_l.x + coat_l.y, 1.0));
    }
    return ((coat + t * spec) * PI + t * diffuse) * nl;
#else
    return (spec * PI + diffuse) * nl;
#endif
}
#endif

#if N_DISTANT > 0
// One orthographic map m: 1 lit, 0 shadowed, -1 uncertain (shadow_maps.filtered_visibility:
// lit when test <= the neighbourhood's min, shadowed when test > its max).
float map_test(sampler2D tex, int m, vec3 p, vec3 n)
{
    int s = map_size[m];
    if (s <= 0) {
        return 1.0;
    }
    vec3 lp = vec3(dot(map_x[m], p), dot(map_y[m], p), dot(map_z[m], p));
    vec2 f = (lp.xy - map_lo[m]) / map_texel[m] - 0.5;
    if (!(f.x > -1.0 && f.x < float(s) && f.y > -1.0 && f.y < float(s))) {
        return 1.0;  // outside the footprint: none of the map's casters is above
    }
    float c = clamp(abs(dot(n, map_z[m])), min_cos, 1.0);
    float tan_angle = sqrt(1.0 - c * c) / c;
    float texel = max(map_texel[m].x, map_texel[m].y);
    float test = -lp.z - texel * (bias_texels + slope_bias_texels * tan_angle);
    ivec2 t = clamp(ivec2(roundEven(f)), ivec2(0), ivec2(s - 1));
    vec2 mm = texelFetch(tex, t, 0).rg;
    if (test <= mm.x) {
        return 1.0;
    }
    return test > mm.y ? 0.0 : -1.0;
}

// DistantLight k through both its maps: lit pairs are shaded, uncertain ones flagged.
void distant(int k, float vs, float vd, Surface s, vec3 n, vec3 e, float nv,
             inout vec3 d_sum, inout float unsure)
{
    if (vs == 0.0 || vd == 0.0) {
        return;
    }
    if (vs < 0.0 || vd < 0.0) {
        unsure += float(1 << (16 + k));
        return;
    }
    d_sum += distant_radiance[k] * brdf_cos(s, n, e, distant_dir[k], nv);
}
#endif

#if SHADE && AREA
// The angle atan(y, x) in [0, pi] for y >= 0, to float32's rounding: the edges' terms
// of a light seen near its plane cancel to a small sum, which llvmpipe's own atan (a
// coarser polynomial) left ~1 % off. Reduced to t in [0, 1], then to |z| <= tan(pi/12)
// (atan t = pi/6 + atan((sqrt(3) t - 1) / (t + sqrt(3)))), where atan's series to z^11
// is within 1e-8 of z.
float edge_angle(float y, float x)
{
    bool swap = y > abs(x);
    float t = swap ? abs(x) / y : y / max(abs(x), 1e-30);
    bool shift = t > 0.26794919;
    float z = shift ? (1.7320508 * t - 1.0) / (t + 1.7320508) : t;
    float z2 = z * z;
    float a = z * (1.0 + z2 * (-1.0 / 3.0 + z2 * (0.2 + z2 * (-1.0 / 7.0 + z2 * (1.0 / 9.0
                                                                    - z2 / 11.0)))));
    a = shift ? a + PI / 6.0 : a;
    a = swap ? 0.5 * PI - a : a;
    return x < 0.0 ? PI - a : a;
}

// Lambert's term of one edge (a, b) of a light's outline seen from the point (its
// corners relative to it): the angle it subtends times n.ĝ, ĝ the unit normal of the
// plane through it and the point (area_light_kernels._unshadowed; the angle from
// |a x b| and a.b rather than acos, which float32 rounds to nothing for a far edge).
float edge_term(vec3 a, vec3 b, vec3 n)
{
    vec3 g = cross(a, b);
    float lg = length(g);
    return lg > 0.0 ? edge_angle(lg, dot(a, b)) * dot(n, g) / lg : 0.0;
}

// Light li's area factor at a point of unit normal n that sees the light's centre at
// -v, dist2 = max(|v|², min distance²) (area_light_kernels._factor, GLSL's only copy:
// tests/engine/test_area_light_shading.py ties the two): the light's exact unshadowed
// irradiance (Lambert's formula over its outline, a disk as a regular polygon of its
// area, clipped to the point's horizon) over the point light's, A n.l / d², at most
// 1e30; 1 for a light that is no area, 0 behind the light or for a light of no area.
float area_factor(int li, vec3 v, float dist2, vec3 n)
{
    vec4 u = light_texel(li, 3);
    float factor = 1.0;
    // A loop of at most one pass rather than an if: llvmpipe runs an if's code for every
    // lane whether any takes it or not, but skips a loop no lane enters, so the pairs of
    // point lights (a group of fragments walks one light at a time) pay nothing here.
    for (int once = u.w == 0.0 ? 1 : 0; once < 1; ++once) {
        vec3 w = light_texel(li, 4).xyz;
        vec3 c = -v;
        float nc = dot(n, c);
        bool rect = u.w == 1.0;
        bool front = dot(c, light_texel(li, 5).xyz) < 0.0 && nc > 0.0;
        int m = front ? (rect ? 4 : DISK_CORNERS) : 0;
        // The outline's corners (area_light_kernels._unshadowed's order) by turning the
        // first, (a, b) in units of (u, w), a step at a time: a quarter turn for a rect's
        // (±1, ±1), 2 pi / m for a disk's polygon DISK_SCALE radii out.
        vec2 ab = rect ? vec2(-1.0, -1.0) : vec2(DISK_SCALE, 0.0);
        float phi = 2.0 * PI / float(DISK_CORNERS);
        vec2 turn = rect ? vec2(0.0, 1.0) : vec2(cos(phi), sin(phi));
        // The outline clipped to the horizon n.x >= 0 edge by edge: the kept parts of its
        // edges, and the chord along the horizon from where it leaves to where it comes
        // back (a convex outline leaves at most once).
        float total = 0.0;
        vec3 leaves = vec3(0.0);
        vec3 returns = vec3(0.0);
        vec3 a = c + ab.x * u.xyz + ab.y * w;
        float ha = dot(n, a);
        for (int k = 1; k <= m; ++k) {
            ab = vec2(ab.x * turn.x - ab.y * turn.y, ab.y * turn.x + ab.x * turn.y);
            vec3 b = c + ab.x * u.xyz + ab.y * w;
            float hb = dot(n, b);
            if (ha >= 0.0 && hb >= 0.0) {
                total += edge_term(a, b, n);
            } else if (ha >= 0.0) {
                leaves = a + ha / (ha - hb) * (b - a);
                total += edge_term(a, leaves, n);
            } else if (hb >= 0.0) {
                returns = a + ha / (ha - hb) * (b - a);
                total += edge_term(returns, b, n);
            }
            a = b;
            ha = hb;
        }
        total += edge_term(leaves, returns, n);  // 0 where nothing was clipped
        float area = (rect ? 4.0 : PI) * length(cross(u.xyz, w));
        float point = area * nc * inversesqrt(dist2) / dist2;  // A n.l / d²
        factor = front && point > 0.0 ? min(0.5 * abs(total) / point, 1e30) : 0.0;
    }
    return factor;
}
#endif

#if SHADE
// Adds light li's contribution at a point it lights (the shadow test said lit); v and
// d2 as in lookup (shared: the compiler would not match light - p with p - light).
void shade(int li, vec3 v, float d2, Surface s, vec3 n, vec3 e, float nv, inout vec3 d_sum)
{
    float r = light_texel(li, 0).w;
    float r2 = r * r;
    float dist2 = max(d2, min_light_distance * min_light_distance);
    float inv_d = inversesqrt(dist2);
    vec3 l = -v * inv_d;
    float q = dist2 / r2;
    float window = clamp(1.0 - q * q, 0.0, 1.0);
    float e_light = window * window * (inv_d * inv_d);
#if AREA
    e_light *= area_factor(li, v, dist2, n);
#endif
    d_sum += light_texel(li, 1).xyz * (e_light * brdf_cos(s, n, e, l, nv));
}
#endif

// The light in slot j of tile ``tile`` (-1: none).
int slot_light(ivec2 tile, int j)
{
#if TILED
    return texelFetch(tile_slots, ivec2(tile.x + j, tile.y), 0).r;
#else
    return j;
#endif
}

void main()
{
    ivec2 xy = ivec2(gl_FragCoord.xy);
    int k = xy.y * width + xy.x;
#if TILED
    int t = texelFetch(point_tiles, xy, 0).r;
    ivec2 tile = ivec2(N_SLOTS * (t % SLOT_TILES), t / SLOT_TILES);  // its first slot
#else
    ivec2 tile = ivec2(0);
#endif
    float result[16];
    for (int j = 0; j < 16; ++j) {
        result[j] = 0.0;
    }
    vec3 d_sum = vec3(0.0);
    float unsure = 0.0;
    if (k < n_points) {
        vec3 p = texelFetch(points, xy, 0).xyz;
        vec3 n = texelFetch(normals, xy, 0).xyz;
#if TERMINATOR
        vec3 ng = texelFetch(terminator, xy, 0).xyz;
        vec3 lift = vec3(0.0);
        // Only a point that moves reads its move: a loop of at most one pass rather than
        // an if, which llvmpipe skips where no fragment of a group moves (a flat region).
        for (int once = dot(ng, ng) > 0.0 ? 0 : 1; once < 1; ++once) {
            lift = texelFetch(lifts, xy, 0).xyz;
        }
#else
        vec3 ng = vec3(0.0);
        vec3 lift = vec3(0.0);
#endif
#if SHADE
        vec3 e = texelFetch(to_eye, xy, 0).xyz;
        float nv = max(dot(n, e), min_cosine);
        Surface s = surface_at(xy, nv);
#endif
#if N_DISTANT > 0
        if (dot(n, distant_dir[0]) > 0.0) {  // facing away: no light, nothing to decide
            vec3 q = p;
#if TERMINATOR
            q += terminator_move(lift, ng, dot(ng, distant_dir[0]), 1.0);
#endif
            distant(0, map_test(dmap_s0, 0, q, n), map_test(dmap_d0, 1, q, n), s, n, e, nv,
                    d_sum, unsure);
        }
#endif
#if N_DISTANT > 1
        if (dot(n, distant_dir[1]) > 0.0) {
            vec3 q = p;
#if TERMINATOR
            q += terminator_move(lift, ng, dot(ng, distant_dir[1]), 1.0);
#endif
            distant(1, map_test(dmap_s1, 2, q, n), map_test(dmap_d1, 3, q, n), s, n, e, nv,
                    d_sum, unsure);
        }
#endif
#if SHADE && N_LIGHTS > 0
        // llvmpipe runs a branch's code for all its lanes whether any takes it or not,
        // but leaves a loop once no lane goes on: the lights are walked as bit masks,
        // so a group of fragments costs the most lights one of them has to look up
        // (in range, facing it: ~8 of the sewer's 13) and then to shade (lit), not
        // every light twice (sewer 640x480: ~20 % less time for the pass). The lights
        // go in increasing order either way, so the sums are the same.
        // The slots are the tile's lights: those whose range reaches none of its points
        // are not in them (light_pass.LOOKUP_TILE), so a fragment walks the few lights
        // near it whatever the stage's count.
        uint todo = 0u;  // bit j: slot j's light can light the point (lookup's reach)
        for (int j = 0; j < N_LIGHTS; ++j) {
            int li = slot_light(tile, j);
            vec4 pr = light_texel(max(li, 0), 0);
            vec3 v = p - pr.xyz;
            todo |= (li >= 0 && dot(v, v) < pr.w * pr.w && dot(n, v) < 0.0) ? (1u << j) : 0u;
        }
        uint lit = 0u;
        // (Lanes already done run the loop masked with findLSB(0) = -1: ``& 15`` keeps
        // their uniform reads inside the arrays; what they compute is discarded.)
        while (todo != 0u) {
            int j = findLSB(todo) & 15;
            todo &= todo - 1u;
            int li = max(slot_light(tile, j), 0);
            vec3 v = p - light_texel(li, 0).xyz;
            float vis = lookup(li, v, dot(v, v), n, ng, lift);
            if (vis > 0.5) {
                lit |= 1u << j;
            } else if (vis < -0.5) {
                unsure += float(1 << j);
            }
        }
        while (lit != 0u) {
            int j = findLSB(lit) & 15;
            lit &= lit - 1u;
            int li = max(slot_light(tile, j), 0);
            vec3 v = p - light_texel(li, 0).xyz;
            shade(li, v, dot(v, v), s, n, e, nv, d_sum);
        }
#elif !SHADE
        // Constant trip count: the compiler unrolls it, so every index of ``result``
        // is a constant (dynamic indexing of local arrays is slow in llvmpipe; the
        // loops above index only uniform arrays by a variable light).
        for (int j = 0; j < N_LIGHTS; ++j) {
            int li = slot_light(tile, j);
            vec3 v = p - light_texel(max(li, 0), 0).xyz;
            result[j] = li >= 0 ? lookup(li, v, dot(v, v), n, ng, lift) : 0.0;
        }
#endif
    }
#if SHADE
    direct = vec4(d_sum, unsure);
#else
    uint word[4];
    for (int c = 0; c < 4; ++c) {
        word[c] = code(result[4 * c]) | (code(result[4 * c + 1]) << 8)
            | (code(result[4 * c + 2]) << 16) | (code(result[4 * c + 3]) << 24);
    }
    codes = uvec4(word[0], word[1], word[2], word[3]);
#endif
}
