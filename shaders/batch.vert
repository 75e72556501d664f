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
uniform int tiles;                // tiles per pass, stacked in one column
uniform int segment_base;         // segmentation id of this group's instance 0

#ifdef FLAT_FACES
flat out vec4 v_color;  // shared corners: the provoking (last) vertex carries its face's normal
#else
out vec4 v_color;
#endif
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
    // spills into a neighbour. Tiles span the framebuffer's width (one column), so the
    // viewport clips x; only the top and bottom need planes.
    gl_ClipDistance[0] = clip.w + clip.y;
    gl_ClipDistance[1] = clip.w - clip.y;

    // Tiles are stored top row first in memory (GL reads back bottom-up), so each view is
    // flipped vertically; the renderer flips the cull mode to match.
    gl_Position = vec4(clip.x, (float(2 * pass_view + 1 - tiles) * clip.w - clip.y) / float(tiles), clip.z, clip.w);

#ifdef EFFECT_LIGHTING
    // Normals scale inversely (inverse transpose); a zero scale flattens the mesh, and
    // the normal then points straight out of the flat side.
    vec3 normal = rotate(rotation, normalize(p3d_Normal / max(scale.xyz, vec3(1e-6))));
#endif
#ifdef LIGHT_PER_FRAGMENT
    v_normal = normal;
#endif
#ifdef LIGHT_PER_VERTEX
    // A flat-shaded mesh has one normal per face, so lighting its vertices is exact and
    // spares every pixel the work (a quarter of a frame on a CPU rasteriser).
    v_color.rgb *= ambient_color + light_color * max(dot(normal, -light_direction), 0.0);
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
