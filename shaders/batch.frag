// Colour, then only the declared effects. The renderer reads the render textures back
// with GL itself, in R, G, B(, A) order.
#ifdef EXACT_TILES
// Every input is flat: exact.geom hands over each triangle's values as planes in its view's clip
// space, evaluated here at the pixel's place inside its tile (the rasteriser would interpolate them
// from the framebuffer's origin, with rounding that depends on where the tile sits, so on the
// world's slot and the batch size). Depth too: gl_FragDepth from the plane.
uniform vec2 tile_size;    // (width, height) of a tile in pixels
flat in float g_tile_row;  // the tile's first window row
flat in vec4 g_color;
flat in vec3 g_z_plane;   // . (x/w, y/w, 1) = z/w, the depth the depth test compares
#if defined(LIGHT_PER_FRAGMENT) || defined(EFFECT_TEXTURE) || defined(APPEARANCE_SURFACE) || defined(EFFECT_SHADOWS) || defined(EFFECT_FOG) || defined(LOG_DEPTH)
#define PLANE_W
flat in vec3 g_w_plane;    // . (x/w, y/w, 1) = 1/w
#endif
#ifdef OUTPUT_DEPTH
flat in vec4 depth_plane;  // the triangle's plane n.(x, y, w) = d in its view's clip space
flat in vec4 depth_tile;   // tile origin (pixels), smallest and largest w of the triangle
#endif
#ifdef EFFECT_TEXTURE
flat in mat3x2 g_uv_plane;
vec2 v_uv = vec2(0.0);
uniform sampler2D p3d_Texture0;
#endif
#ifdef LIGHT_PER_FRAGMENT
flat in mat3 g_normal_plane;
vec3 v_normal = vec3(0.0);
#ifdef EFFECT_APPEARANCE
flat in vec3 g_look_light_direction;  // the world's light (batch.vert reads it)
flat in vec3 g_look_light_color;
flat in vec3 g_look_ambient;
#define light_direction g_look_light_direction
#define light_color g_look_light_color
#define ambient_color g_look_ambient
#else
uniform vec3 light_direction;  // world frame, pointing from the light
uniform vec3 light_color;
uniform vec3 ambient_color;
#endif
#endif
#ifdef APPEARANCE_SURFACE
flat in mat3x2 g_surface_plane;  // pattern coordinates, in cells
vec2 v_surface = vec2(0.0);
flat in vec4 g_pattern;  // factors past the line threshold along u only, v only, both (contrast included); threshold
#define v_pattern g_pattern
#endif
#define v_color g_color
#if defined(EFFECT_FOG) || defined(LOG_DEPTH)
float v_depth = float(0.0);
#endif
#ifdef EFFECT_FOG
uniform vec3 fog_color;
uniform float fog_density;  // exponential fog, per metre
#endif
#ifdef LOG_DEPTH
flat in vec2 g_near_far;
#define v_near_far g_near_far
#endif
#ifdef OUTPUT_SEGMENTATION
flat in int g_segment;
#define v_segment g_segment
#endif
#ifdef EFFECT_SHADOWS
flat in mat3 g_light_plane;
vec3 v_light = vec3(0.0);                    // the fragment in the light's clip space
flat in ivec2 g_shadow_tile;
#define v_shadow_tile g_shadow_tile
uniform sampler2D shadow_atlas;  // depth seen from the light, one square tile per world
uniform ivec2 shadow_tiles;      // (tiles per atlas row, texels per tile side)
uniform float shadow_bias;       // depth units: how close a receiver may be to a stored face
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
flat in vec3 g_direct;
#define v_direct g_direct
#endif

#else
#ifdef DEPTH_PLANE_FROM_GEOMETRY
// The geometry shader batch.geom sits between the stages; its outputs are named g_*.
#define v_color g_color
#ifdef LIGHT_PER_FRAGMENT
#define v_normal g_normal
#endif
#ifdef EFFECT_TEXTURE
#define v_uv g_uv
#endif
#define v_depth g_depth
#ifdef LOG_DEPTH
#define v_near_far g_near_far
#endif
#ifdef OUTPUT_SEGMENTATION
#define v_segment g_segment
#endif
#ifdef EFFECT_SHADOWS
#define v_light g_light
#define v_shadow_tile g_shadow_tile
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
#define v_direct g_direct
#endif
#if defined(EFFECT_APPEARANCE) && defined(LIGHT_PER_FRAGMENT)
#define v_look_light_direction g_look_light_direction
#define v_look_light_color g_look_light_color
#define v_look_ambient g_look_ambient
#endif
#ifdef APPEARANCE_SURFACE
#define v_surface g_surface
#define v_pattern g_pattern
#endif
#endif
#ifdef OUTPUT_DEPTH
flat in vec4 depth_plane;  // the triangle's plane n.(x, y, w) = d in its view's clip space
flat in vec4 depth_tile;   // tile origin (pixels), smallest and largest w of the triangle
uniform vec2 tile_size;    // pixels
#endif
flat in vec4 v_color;
#ifdef EFFECT_TEXTURE
in vec2 v_uv;
uniform sampler2D p3d_Texture0;
#endif
#ifdef LIGHT_PER_FRAGMENT
in vec3 v_normal;
#ifdef EFFECT_APPEARANCE
flat in vec3 v_look_light_direction;  // the world's light (batch.vert reads it)
flat in vec3 v_look_light_color;
flat in vec3 v_look_ambient;
#define light_direction v_look_light_direction
#define light_color v_look_light_color
#define ambient_color v_look_ambient
#else
uniform vec3 light_direction;  // world frame, pointing from the light
uniform vec3 light_color;
uniform vec3 ambient_color;
#endif
#endif
#ifdef APPEARANCE_SURFACE
in vec2 v_surface;       // pattern coordinates, in cells
flat in vec4 v_pattern;  // factors past the line threshold along u only, v only, both (contrast included); threshold
#endif
#if defined(EFFECT_FOG) || defined(OUTPUT_DEPTH) || defined(LOG_DEPTH)
in float v_depth;
#endif
#ifdef EFFECT_FOG
uniform vec3 fog_color;
uniform float fog_density;  // exponential fog, per metre
#endif
#ifdef LOG_DEPTH
flat in vec2 v_near_far;
#endif
#ifdef OUTPUT_SEGMENTATION
flat in int v_segment;
#endif
#ifdef EFFECT_SHADOWS
in vec3 v_light;                 // the fragment in the light's clip space
flat in ivec2 v_shadow_tile;
uniform sampler2D shadow_atlas;  // depth seen from the light, one square tile per world
uniform ivec2 shadow_tiles;      // (tiles per atlas row, texels per tile side)
uniform float shadow_bias;       // depth units: how close a receiver may be to a stored face
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
flat in vec3 v_direct;
#endif

#endif

layout(location = 0) out vec4 out_color;
#ifdef OUTPUT_DEPTH
layout(location = DEPTH_LOCATION) out vec4 out_depth;
#endif
#ifdef OUTPUT_SEGMENTATION
layout(location = SEGMENTATION_LOCATION) out vec4 out_segment;
#endif

// A 32-bit value as four exact 8-bit channels, least significant byte in red: read back
// as RGBA bytes, memory then holds the value's little-endian bytes.
vec4 bytes_of(uint bits) {
    return unpackUnorm4x8(bits);
}

#ifdef EFFECT_SHADOWS
// Where this fragment reads its world's tile: the point in texels, the receiver's depth
// there, and the receiver's depth slope per texel (from screen derivatives), so that each
// texel is compared with the receiver's own depth at that texel's centre. Sloped
// receivers then need no slope bias and no shadow moves by more than the texel grid.
struct ShadowLookup {
    ivec2 tile;
    vec2 texel;
    float depth;
    vec2 slope;
};

float shadow_lit(ShadowLookup s, ivec2 texel) {
    ivec2 inside = clamp(texel, ivec2(0), ivec2(shadow_tiles.y - 1));  // never a neighbour's tile
    float receiver = s.depth + dot(s.slope, vec2(inside) + 0.5 - s.texel);
    return receiver < texelFetch(shadow_atlas, s.tile + inside, 0).r ? 1.0 : 0.0;
}

// The fraction of the directional light that reaches this fragment. Outside the light's
// box (Shadows.bounds) everything is lit.
float light_visibility() {
    vec3 p = v_light * 0.5 + 0.5;
    int size = shadow_tiles.y;
    ShadowLookup s;
    s.texel = vec2(p.x, 1.0 - p.y) * float(size);  // tiles are flipped vertically, like views
    // Derivatives before any branch: they need the whole 2x2 quad of pixels.
    vec3 dx = dFdx(vec3(s.texel, p.z));
    vec3 dy = dFdy(vec3(s.texel, p.z));
    float det = dx.x * dy.y - dx.y * dy.x;
    s.slope = abs(det) > 1e-12 ? vec2(dx.z * dy.y - dx.y * dy.z, dx.x * dy.z - dx.z * dy.x) / det : vec2(0.0);
    if (any(lessThan(p, vec3(0.0))) || any(greaterThan(p, vec3(1.0)))) {
        return 1.0;
    }
    s.tile = v_shadow_tile;
    // The map holds the faces turned away from the light. A receiver level with one
    // touches it (the floor under a box): in shadow. Smooth normals light faces a little
    // past the silhouette, so there a receiver level with its own back face stays lit.
#ifdef LIGHT_PER_VERTEX
    s.depth = p.z + shadow_bias;
#else
    s.depth = p.z - shadow_bias;
#endif
#ifdef SHADOW_PCF
    // Four compares around the point, weighted bilinearly: edges soft over one texel.
    vec2 corner = s.texel - 0.5;
    ivec2 base = ivec2(floor(corner));
    vec2 f = corner - floor(corner);
    float below = mix(shadow_lit(s, base), shadow_lit(s, base + ivec2(1, 0)), f.x);
    float above = mix(shadow_lit(s, base + ivec2(0, 1)), shadow_lit(s, base + ivec2(1, 1)), f.x);
    return mix(below, above, f.y);
#else
    return shadow_lit(s, ivec2(floor(s.texel)));
#endif
}
#endif

#ifdef APPEARANCE_SURFACE
// The factor a floor's or wall's pattern leaves of its colour, from where the fragment lies (no
// texture). One formula for every pattern, no branch (llvmpipe would run every branch anyway):
// whether the fragment lies past the threshold along u and along v within its cell picks one of
// four factors, 1 where it is past neither. appearance.py sets them per pattern (checker: u or v
// but not both, stripes: u, dots: both, bricks: u or v with every other row shifted by half a
// cell v_color.a; plain: all 1).
float surface_pattern() {
    vec2 inside = fract(vec2(v_surface.x + v_color.a * floor(v_surface.y), v_surface.y));
    bvec2 past = greaterThanEqual(inside, vec2(v_pattern.w));
    return past.y ? (past.x ? v_pattern.z : v_pattern.y) : (past.x ? v_pattern.x : 1.0);
}
#endif

void main() {
#ifdef EXACT_TILES
    // The pixel's centre in its view's clip space over w: (x/w, y/w, 1), from its place in its
    // tile (tiles are flipped vertically).
    vec2 tile_pixel = (gl_FragCoord.xy - vec2(0.0, g_tile_row)) / tile_size * 2.0 - 1.0;
    vec3 pixel = vec3(tile_pixel.x, -tile_pixel.y, 1.0);
#ifdef PLANE_W
    float inverse_w = dot(g_w_plane, pixel);
#endif
#ifdef LIGHT_PER_FRAGMENT
    v_normal = g_normal_plane * pixel;  // normalised below
#endif
#ifdef EFFECT_TEXTURE
    v_uv = g_uv_plane * pixel / inverse_w;
#endif
#ifdef APPEARANCE_SURFACE
    v_surface = g_surface_plane * pixel / inverse_w;
#endif
#ifdef EFFECT_SHADOWS
    v_light = g_light_plane * pixel / inverse_w;
#endif
#if defined(EFFECT_FOG) || defined(LOG_DEPTH)
    v_depth = 1.0 / inverse_w;
#endif
    float depth_ndc = dot(g_z_plane, pixel);
    if (depth_ndc > 1.0) {
        discard;  // beyond the far plane (exact.geom clips only the others)
    }
#ifndef LOG_DEPTH
    gl_FragDepth = 0.5 * depth_ndc + 0.5;
#endif
#endif
    vec3 color = v_color.rgb;
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
    color += v_direct * light_visibility();
#endif
#ifdef EFFECT_TEXTURE
    color *= texture(p3d_Texture0, v_uv).rgb;
#endif
#ifdef APPEARANCE_SURFACE
    color *= surface_pattern();
#endif
#ifdef LIGHT_PER_FRAGMENT
    float lambert = max(dot(normalize(v_normal), -light_direction), 0.0);
#ifdef EFFECT_SHADOWS
    lambert *= light_visibility();
#endif
    color *= ambient_color + light_color * lambert;
#endif
#ifdef EFFECT_FOG
    color = mix(fog_color, color, exp(-fog_density * v_depth));
#endif
#ifdef OUTPUT_GRAY
    // ITU-R BT.601 luma (shaders.GRAY_WEIGHTS); read back as the red channel only.
    out_color = vec4(vec3(dot(clamp(color, 0.0, 1.0), vec3(0.299, 0.587, 0.114))), 1.0);
#else
    out_color = vec4(clamp(color, 0.0, 1.0), 1.0);
#endif
#ifdef LOG_DEPTH
    // Logarithmic depth: equal relative precision from near to far.
    gl_FragDepth = log2(max(v_depth, v_near_far.x) / v_near_far.x) / log2(v_near_far.y / v_near_far.x);
#endif
#ifdef OUTPUT_DEPTH
    // Depth where this pixel's ray meets the triangle's plane, from the pixel's position
    // inside its tile. An interpolated value would carry rounding that depends on where
    // the tile sits in the framebuffer (the rasteriser evaluates it at absolute pixel
    // positions), so depth would change in its last bits with the tile layout.
    precise vec2 inside_tile = gl_FragCoord.xy - depth_tile.xy;
    precise vec2 ndc = inside_tile / tile_size * 2.0 - 1.0;
    precise float depth = depth_plane.w / dot(depth_plane.xyz, vec3(ndc.x, -ndc.y, 1.0));  // tiles are flipped
    out_depth = bytes_of(floatBitsToUint(clamp(depth, depth_tile.z, depth_tile.w)));
#endif
#ifdef OUTPUT_SEGMENTATION
    out_segment = bytes_of(uint(v_segment));
#endif
}
