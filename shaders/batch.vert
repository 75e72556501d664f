// One instanced draw covers every view of every world. Instance k of the draw is the
// k-th visible (view, instance) pair of this pass, listed by the renderer after
// frustum culling in torch; pairs are sorted by view.
// Effects and group kinds arrive as #defines prepended by marl_render/shaders.py.
in vec4 p3d_Vertex;
in vec3 p3d_Normal;
#ifdef EFFECT_TEXTURE
in vec2 p3d_MultiTexCoord0;
out vec2 v_uv;
#endif

uniform samplerBuffer instances;  // INSTANCE_TEXELS texels per instance, see renderer.py
uniform samplerBuffer views;      // VIEW_TEXELS texels per view
uniform isamplerBuffer pairs;     // view * capacity + instance, visible pairs only
uniform int pair_offset;          // first pair of this pass
uniform int capacity;             // instances per world in this group
uniform int agents;               // views per world
uniform int view_offset;          // first view drawn by this pass
uniform ivec2 grid;               // tiles per pass (columns, rows)
uniform int segment_base;         // segmentation id of this group's instance 0

out vec4 v_color;
#ifdef LIGHT_PER_FRAGMENT
out vec3 v_normal;
#endif
#ifdef LIGHT_PER_VERTEX
uniform vec3 light_direction;  // world frame, pointing from the light
uniform vec3 light_color;
uniform vec3 ambient_color;
#endif
#if defined(EFFECT_FOG) || defined(OUTPUT_DEPTH) || defined(LOG_DEPTH)
out float v_depth;
#endif
#ifdef LOG_DEPTH
flat out vec2 v_near_far;
#endif
#ifdef OUTPUT_SEGMENTATION
flat out int v_segment;
#endif
#ifdef EFFECT_SHADOWS
uniform samplerBuffer lights;  // per world: the light's view-projection (texels 0-3), as views
uniform ivec2 shadow_tiles;    // (tiles per atlas row, texels per tile side)
out vec3 v_light;              // the vertex in the light's clip space (orthographic: w = 1)
flat out ivec2 v_shadow_tile;  // first texel of this world's tile in the atlas
#endif
#if defined(EFFECT_SHADOWS) && defined(LIGHT_PER_VERTEX)
out vec3 v_direct;             // the directional light's share of the colour, dimmed per fragment
#endif

vec3 rotate(vec4 q, vec3 v) {
    vec3 t = 2.0 * cross(q.yzw, v);
    return v + q.x * t + cross(q.yzw, t);
}

void main() {
    int pair = texelFetch(pairs, pair_offset + gl_InstanceID).x;
    int view = pair / capacity;
    int instance = pair - view * capacity;
    int pass_view = view - view_offset;
    int world = view / agents;

#ifdef STATIC_GROUP
    int row = instance * INSTANCE_TEXELS;      // shared by all worlds
#else
    int row = (world * capacity + instance) * INSTANCE_TEXELS;
#endif
    vec4 position = texelFetch(instances, row);      // xyz (w: active, used by culling)
    vec4 rotation = texelFetch(instances, row + 1);  // unit quaternion (w, x, y, z)
    vec4 scale = texelFetch(instances, row + 2);     // xyz (w: owner, used by culling)
    v_color = texelFetch(instances, row + 3);

    int vrow = view * VIEW_TEXELS;
    mat4 view_projection = mat4(texelFetch(views, vrow), texelFetch(views, vrow + 1),
                                texelFetch(views, vrow + 2), texelFetch(views, vrow + 3));
#ifdef STATIC_GROUP
    // Positions relative to the world's origin in two floats each (hi + lo), so that
    // scenes far from 0 keep sub-millimetre precision.
    vec3 relative = (position.xyz - texelFetch(views, vrow + 4).xyz)
                  + (texelFetch(instances, row + 4).xyz - texelFetch(views, vrow + 5).xyz);
#else
    vec3 relative = position.xyz;  // already relative to the world's origin
#endif
    vec3 world_position = relative + rotate(rotation, p3d_Vertex.xyz * scale.xyz);
    vec4 clip = view_projection * vec4(world_position, 1.0);

    // Clip against this view's own frustum before moving it into its tile, so nothing
    // spills into a neighbour.
    gl_ClipDistance[0] = clip.w + clip.x;
    gl_ClipDistance[1] = clip.w - clip.x;
    gl_ClipDistance[2] = clip.w + clip.y;
    gl_ClipDistance[3] = clip.w - clip.y;

    // Tiles are stored top row first in memory (glReadPixels reads bottom-up), so each
    // view is flipped vertically; the renderer flips the cull mode to match.
    int tile_x = pass_view % grid.x;
    int tile_y = pass_view / grid.x;
    vec2 flipped = vec2(clip.x, -clip.y);
    vec2 tile_shift = vec2(2 * tile_x + 1 - grid.x, 2 * tile_y + 1 - grid.y);
    gl_Position = vec4((flipped + clip.w * tile_shift) / vec2(grid), clip.z, clip.w);

#ifdef EFFECT_LIGHTING
    // Normals scale inversely (inverse transpose); a zero scale flattens the mesh, and
    // the normal then points straight out of the flat side.
    vec3 normal = rotate(rotation, normalize(p3d_Normal / max(scale.xyz, vec3(1e-6))));
#endif
#ifdef LIGHT_PER_FRAGMENT
    v_normal = normal;
#endif
#if defined(LIGHT_PER_VERTEX) && defined(EFFECT_SHADOWS)
    // Shadows vary within a face: keep the direct light apart for the fragment stage.
    v_direct = v_color.rgb * light_color * max(dot(normal, -light_direction), 0.0);
    v_color.rgb *= ambient_color;
#elif defined(LIGHT_PER_VERTEX)
    // A flat-shaded mesh has one normal per face, so lighting its vertices is exact and
    // spares every pixel the work (a quarter of a frame on a CPU rasteriser).
    v_color.rgb *= ambient_color + light_color * max(dot(normal, -light_direction), 0.0);
#endif
#ifdef EFFECT_SHADOWS
    int lrow = world * VIEW_TEXELS;
    mat4 light_projection = mat4(texelFetch(lights, lrow), texelFetch(lights, lrow + 1),
                                 texelFetch(lights, lrow + 2), texelFetch(lights, lrow + 3));
    v_light = (light_projection * vec4(world_position, 1.0)).xyz;
    v_shadow_tile = ivec2(world % shadow_tiles.x, world / shadow_tiles.x) * shadow_tiles.y;
#endif
#ifdef EFFECT_TEXTURE
    v_uv = p3d_MultiTexCoord0;
#endif
#if defined(EFFECT_FOG) || defined(OUTPUT_DEPTH) || defined(LOG_DEPTH)
    v_depth = clip.w;
#endif
#ifdef LOG_DEPTH
    v_near_far = vec2(texelFetch(views, vrow + 4).w, texelFetch(views, vrow + 5).w);
#endif
#ifdef OUTPUT_SEGMENTATION
    v_segment = segment_base + instance;
#endif
}
