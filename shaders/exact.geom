// The geometry stage of BatchRenderer(exact_tiles=True): every triangle of every view passes
// here in its view's own clip space (batch.vert) and leaves in its tile. The rasteriser (llvmpipe)
// works at absolute framebuffer positions: it snaps window positions to 1/256 pixel, clips in the
// clip space it is given and interpolates from the framebuffer's origin. With tiles stacked in one
// column, a float32 window position carries rounding of the order of 2^-24 times its row, so all
// three depend on where the view's tile sits: a vertex snaps 1/256 pixel apart near a midpoint
// (coverage along edges), a clipped vertex lands elsewhere, and depth, normals, patterns, fog and
// shadow coordinates change in their last bits. A world's pixels then depend on its slot and on
// the batch size. So this stage does that work where the tile plays no part:
// - it clips the triangle against the view's frustum itself, in the view's clip space;
// - it snaps each vertex's row inside the tile to the 1/256-pixel grid and adds the tile's first
//   row exactly; the position leaves with w = 1, so the GL's divide is exact and its viewport
//   transform adds less than 1/512 pixel (2^-24 of at most 16384 rows, twice), and the GL snaps
//   it to the same point;
// - it hands the fragment stage every varying, depth included, as a flat plane of the whole
//   triangle, which the fragment stage evaluates at the pixel's place inside its tile.
layout(triangles) in;
layout(triangle_strip, max_vertices = 8) out;  // a triangle clipped by 5 planes: 8 corners at most

uniform int tiles;       // tiles in this framebuffer, stacked in one column
uniform vec2 tile_size;  // (width, height) of a tile in pixels

flat in float v_tile_row[];  // the first window row of the vertex's tile
flat in vec4 v_color[];
flat out vec4 g_color;
#if defined(LIGHT_PER_FRAGMENT) || defined(EFFECT_TEXTURE) || defined(APPEARANCE_SURFACE) || defined(EFFECT_SHADOWS) || defined(EFFECT_FOG) || defined(LOG_DEPTH)
#define PLANE_W
// (1, 1, 1) times the inverse of the corners' clip (x, y, w): its dot product with a pixel's
// (x/w, y/w, 1) is 1/w there; the same with an attribute's corners gives attribute/w.
flat out vec3 g_w_plane;
#endif
#ifdef LIGHT_PER_FRAGMENT
in vec3 v_normal[];
flat out mat3 g_normal_plane;  // times (x/w, y/w, 1): the normal over w (direction only is used)
#endif
#ifdef EFFECT_TEXTURE
in vec2 v_uv[];
flat out mat3x2 g_uv_plane;
#endif
#ifdef LOG_DEPTH
flat in vec2 v_near_far[];
flat out vec2 g_near_far;
#endif
#ifdef OUTPUT_SEGMENTATION
flat in int v_segment[];
flat out int g_segment;
#endif
#ifdef EFFECT_SHADOWS
in vec3 v_light[];
flat out mat3 g_light_plane;
flat in ivec2 v_shadow_tile[];
flat out ivec2 g_shadow_tile;
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
flat in vec3 v_direct[];
flat out vec3 g_direct;
#endif
#if defined(EFFECT_APPEARANCE) && defined(LIGHT_PER_FRAGMENT)
flat in vec3 v_look_light_direction[];
flat out vec3 g_look_light_direction;
flat in vec3 v_look_light_color[];
flat out vec3 g_look_light_color;
flat in vec3 v_look_ambient[];
flat out vec3 g_look_ambient;
#endif
#ifdef APPEARANCE_SURFACE
in vec2 v_surface[];
flat out mat3x2 g_surface_plane;
flat in vec4 v_pattern[];
flat out vec4 g_pattern;
#endif
#ifdef OUTPUT_DEPTH
flat out vec4 depth_plane;  // n.(x, y, w) = d in the view's clip space
flat out vec4 depth_tile;   // tile origin (pixels), smallest and largest w of the triangle
#endif
flat out float g_tile_row;  // the tile's first window row, for the fragment stage
flat out vec3 g_z_plane;    // . (x/w, y/w, 1) = z/w: depth for the depth test

// The view's frustum in its clip space: inside where dot(plane, position) >= 0. The far plane
// (last) only drops triangles wholly beyond it; the fragment stage drops what lies beyond it, so
// clipping stops at the first five planes.
const vec4 FRUSTUM[6] = vec4[6](vec4(0.0, 0.0, 1.0, 1.0),                             // near
                                vec4(1.0, 0.0, 0.0, 1.0), vec4(-1.0, 0.0, 0.0, 1.0),   // left, right
                                vec4(0.0, 1.0, 0.0, 1.0), vec4(0.0, -1.0, 0.0, 1.0),   // bottom, top
                                vec4(0.0, 0.0, -1.0, 1.0));                            // far

// The triangle's flat values, computed once; outputs are undefined after each EmitVertex, so
// set_outputs() writes them again for every vertex.
mat3 weights = mat3(1.0);  // inverse of the corners' clip (x, y, w) as columns: barycentrics over w at (x/w, y/w, 1)
#ifdef OUTPUT_DEPTH
vec4 plane = vec4(0.0);
vec2 w_range = vec2(0.0);
#endif

void set_outputs() {
    g_color = v_color[2];  // the provoking (last) vertex's, as without this stage
    g_tile_row = v_tile_row[0];
    g_z_plane = vec3(gl_in[0].gl_Position.z, gl_in[1].gl_Position.z, gl_in[2].gl_Position.z) * weights;
#ifdef PLANE_W
    g_w_plane = vec3(1.0) * weights;
#endif
#ifdef LIGHT_PER_FRAGMENT
    g_normal_plane = mat3(v_normal[0], v_normal[1], v_normal[2]) * weights;
#endif
#ifdef EFFECT_TEXTURE
    g_uv_plane = mat3x2(v_uv[0], v_uv[1], v_uv[2]) * weights;
#endif
#ifdef LOG_DEPTH
    g_near_far = v_near_far[2];
#endif
#ifdef OUTPUT_SEGMENTATION
    g_segment = v_segment[2];
#endif
#ifdef EFFECT_SHADOWS
    g_light_plane = mat3(v_light[0], v_light[1], v_light[2]) * weights;
    g_shadow_tile = v_shadow_tile[2];
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
    g_direct = v_direct[2];
#endif
#if defined(EFFECT_APPEARANCE) && defined(LIGHT_PER_FRAGMENT)
    g_look_light_direction = v_look_light_direction[2];
    g_look_light_color = v_look_light_color[2];
    g_look_ambient = v_look_ambient[2];
#endif
#ifdef APPEARANCE_SURFACE
    g_surface_plane = mat3x2(v_surface[0], v_surface[1], v_surface[2]) * weights;
    g_pattern = v_pattern[2];
#endif
#ifdef OUTPUT_DEPTH
    depth_plane = plane;
    depth_tile = vec4(0.0, v_tile_row[0], w_range);
#endif
}

void emit(vec4 clip) {
    float height = tile_size.y;
    float rows = float(tiles) * height;
    // Rows from the tile's bottom edge: tiles are stored top row first in memory (GL reads back
    // bottom-up), so each view is flipped vertically; the renderer flips the cull mode to match.
    float row = clamp(floor(0.5 * height * (1.0 - clip.y / clip.w) * 256.0 + 0.5) / 256.0, 0.0, height);
    // z inside [-1, 1], so that the GL clips nothing: the fragment stage writes depth from the
    // triangle's plane and drops what lies beyond the far plane.
    gl_Position = vec4(clip.x / clip.w, (2.0 * (v_tile_row[0] + row) - rows) / rows,
                       clamp(clip.z / clip.w, -1.0, 1.0), 1.0);
    set_outputs();
    EmitVertex();
}

void main() {
    vec4 corner[3] = vec4[3](gl_in[0].gl_Position, gl_in[1].gl_Position, gl_in[2].gl_Position);
    // Outside one plane with all three corners: nothing to draw. Inside all: no clipping.
    bool inside_all = true;
    for (int k = 0; k < 6; ++k) {
        vec3 d = vec3(dot(FRUSTUM[k], corner[0]), dot(FRUSTUM[k], corner[1]), dot(FRUSTUM[k], corner[2]));
        if (all(lessThan(d, vec3(0.0)))) {
            return;
        }
        inside_all = inside_all && all(greaterThanEqual(d, vec3(0.0)));
    }
    weights = inverse(mat3(corner[0].xyw, corner[1].xyw, corner[2].xyw));
#ifdef OUTPUT_DEPTH
    vec3 q0 = corner[0].xyw, q1 = corner[1].xyw, q2 = corner[2].xyw;
    vec3 plane_normal = cross(q1 - q0, q2 - q0);
    plane = vec4(plane_normal, dot(plane_normal, q0));
    w_range = vec2(min(q0.z, min(q1.z, q2.z)), max(q0.z, max(q1.z, q2.z)));
#endif

    if (inside_all) {
        emit(corner[0]);
        emit(corner[1]);
        emit(corner[2]);
        EndPrimitive();
        return;
    }
    // Sutherland-Hodgman, one plane at a time. A point on an edge is always computed from the
    // edge's inside end towards its outside end, so the neighbour that shares the edge gets
    // the same point (no cracks).
    vec4 polygon[9] = vec4[9](corner[0], corner[1], corner[2], vec4(0.0), vec4(0.0), vec4(0.0), vec4(0.0),
                              vec4(0.0), vec4(0.0));
    int count = 3;
    // Stage k holds at most 3 + k corners: constant bounds, so the loops unroll and only the writes
    // index by a count that differs between triangles.
#define CLIP_STAGE(k)                                                                              \
    {                                                                                              \
        vec4 kept[9];                                                                              \
        int kept_count = 0;                                                                        \
        for (int i = 0; i < 3 + k; ++i) {                                                          \
            vec4 a = polygon[i];                                                                   \
            vec4 b = i + 1 < count ? polygon[(i + 1) % 9] : polygon[0];                            \
            float da = dot(FRUSTUM[k], a);                                                         \
            float db = dot(FRUSTUM[k], b);                                                         \
            bool live = i < count;                                                                 \
            if (live && da >= 0.0) {                                                               \
                kept[kept_count++] = a;                                                            \
            }                                                                                      \
            if (live && (da >= 0.0) != (db >= 0.0)) {                                              \
                kept[kept_count++] = da >= 0.0 ? mix(a, b, da / (da - db)) : mix(b, a, db / (db - da)); \
            }                                                                                      \
        }                                                                                          \
        polygon = kept;                                                                            \
        count = kept_count;                                                                        \
    }
    CLIP_STAGE(0)
    CLIP_STAGE(1)
    CLIP_STAGE(2)
    CLIP_STAGE(3)
    CLIP_STAGE(4)
    if (count < 3) {
        return;
    }
    // The convex polygon as one strip: 0, 1, n-1, 2, n-2, ... (the winding is kept).
    int low = 0;
    int high = count - 1;
    emit(polygon[0]);
    for (int i = 1; i < 9; ++i) {
        if (i >= count) {
            break;
        }
        if (i % 2 == 1) {
            low += 1;
            emit(polygon[low]);
        } else {
            emit(polygon[high]);
            high -= 1;
        }
    }
    EndPrimitive();
}
