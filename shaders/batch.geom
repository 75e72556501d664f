// Only with the depth output, for meshes from model files and skinned meshes (procedural
// meshes carry their triangles' corners instead, see marl_render/triangle_corners.py; a
// skinned triangle's corners follow joints of their own, so only the skinned positions
// arriving here give its plane): passes each triangle through unchanged and adds its
// plane in its view's own clip space, from which the fragment shader computes depth at
// the pixel's position inside the tile. That makes depth independent of where the tile
// sits, so of the tile layout.
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;

flat in vec4 v_color[];
flat out vec4 g_color;
#ifdef LIGHT_PER_FRAGMENT
in vec3 v_normal[];
out vec3 g_normal;
#endif
#ifdef EFFECT_TEXTURE
in vec2 v_uv[];
out vec2 g_uv;
#endif
in float v_depth[];
out float g_depth;
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
out vec3 g_light;
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
out vec2 g_surface;
flat in vec4 v_pattern[];
flat out vec4 g_pattern;
#endif
in vec3 v_clip[];              // (x, y, w) before the move into the tile
flat in vec2 v_tile_origin[];
#ifdef LAYERED_VIEWS
flat in int v_layer[];
#endif
flat out vec4 depth_plane;     // n.(x, y, w) = d
flat out vec4 depth_tile;      // tile origin, smallest and largest w

void main() {
    vec3 normal = cross(v_clip[1] - v_clip[0], v_clip[2] - v_clip[0]);
    vec4 plane = vec4(normal, dot(normal, v_clip[0]));
    vec2 w_range = vec2(min(v_clip[0].z, min(v_clip[1].z, v_clip[2].z)),
                        max(v_clip[0].z, max(v_clip[1].z, v_clip[2].z)));
    for (int i = 0; i < 3; ++i) {
        gl_Position = gl_in[i].gl_Position;
        // The vertex shader's clip distances, which a geometry shader must write again
        // (tiles span the framebuffer's width, so only the top and bottom: see batch.vert).
#ifdef LAYERED_VIEWS
        gl_Layer = v_layer[0];  // one layer per view, no tile to clip to
#else
        gl_ClipDistance[0] = v_clip[i].z + v_clip[i].y;
        gl_ClipDistance[1] = v_clip[i].z - v_clip[i].y;
#endif
        g_color = v_color[i];
#ifdef LIGHT_PER_FRAGMENT
        g_normal = v_normal[i];
#endif
#ifdef EFFECT_TEXTURE
        g_uv = v_uv[i];
#endif
        g_depth = v_depth[i];
#ifdef LOG_DEPTH
        g_near_far = v_near_far[i];
#endif
#ifdef OUTPUT_SEGMENTATION
        g_segment = v_segment[i];
#endif
#ifdef EFFECT_SHADOWS
        g_light = v_light[i];
        g_shadow_tile = v_shadow_tile[i];
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
        g_direct = v_direct[i];
#endif
#if defined(EFFECT_APPEARANCE) && defined(LIGHT_PER_FRAGMENT)
        g_look_light_direction = v_look_light_direction[i];
        g_look_light_color = v_look_light_color[i];
        g_look_ambient = v_look_ambient[i];
#endif
#ifdef APPEARANCE_SURFACE
        g_surface = v_surface[i];
        g_pattern = v_pattern[i];
#endif
        depth_plane = plane;
        depth_tile = vec4(v_tile_origin[i], w_range);
        EmitVertex();
    }
    EndPrimitive();
}
