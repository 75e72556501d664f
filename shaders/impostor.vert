#ifdef LAYERED_VIEWS
// Every view in its own layer of an array texture (BatchRenderer(layered=True)).
#extension GL_ARB_shader_viewport_layer_array : require
#endif
// A sphere impostor (marl_render/impostors.py): each instance of a sphere group is one quad,
// placed in front of the sphere across the cone of rays from the camera that meet it, and the
// fragment stage (impostor.frag) casts the pixel's ray at the sphere itself: a perfect sphere,
// its depth and normal exact, for 4 vertices instead of a mesh's hundreds.
// Everything is done in the instance's own frame, where the sphere has radius 0.5 at the
// origin: an instance's rotation and (any, non-uniform) scale make it an ellipsoid, and lines
// and planes stay lines and planes through that affine map, so the quad still covers it and
// the hit point maps back exactly.
// The same instance, view and pair buffers as batch.vert (layout.py's ROW_* / VIEW_*), and
// the same tiles: views stacked in one column, each clipped to its own tile.
in vec4 p3d_Vertex;  // quad corner (+-1, +-1) and the quad's index in its instance's batch (impostors.quad_node)

uniform samplerBuffer instances;
uniform samplerBuffer views;
uniform isamplerBuffer pairs;
uniform int pair_offset;
uniform int pair_count;  // pairs this pass draws: quads of the last batch past it draw nothing
uniform int capacity;
uniform int agents;
uniform int view_offset;
uniform int tiles;
uniform int segment_base;

flat out vec4 v_color;
out vec3 v_quad;         // this point of the quad, in the instance's frame
flat out vec3 v_eye;     // the camera, in the instance's frame
flat out vec4 v_clip_z;  // clip z of a point p of the instance's frame: dot(v_clip_z, vec4(p, 1))
flat out vec4 v_clip_w;  // and clip w (the distance along the view axis)
#ifdef EFFECT_LIGHTING
flat out vec4 v_rotation;       // the instance's, to turn the normal into the world frame
flat out vec3 v_inverse_scale;  // normals scale inversely
#ifdef EFFECT_APPEARANCE
flat out vec3 v_look_light_direction;
flat out vec3 v_look_light_color;
flat out vec3 v_look_ambient;
#endif
#endif
#ifdef OUTPUT_SEGMENTATION
flat out int v_segment;
#endif
#ifdef LOG_DEPTH
flat out vec2 v_near_far;
#endif
#ifdef EFFECT_APPEARANCE
uniform samplerBuffer appearance;
#endif

const float RADIUS = 0.5;  // meshes.sphere(): diameter 1

vec3 rotate(vec4 q, vec3 v) {
    vec3 t = 2.0 * cross(q.yzw, v);
    return v + q.x * t + cross(q.yzw, t);
}

void main() {
    int drawn = gl_InstanceID * QUADS_PER_INSTANCE + int(p3d_Vertex.z);
    int pair = texelFetch(pairs, pair_offset + min(drawn, pair_count - 1)).x;
    int view = pair / capacity;
    int instance = pair - view * capacity;
    int pass_view = view - view_offset;
    int world = view / agents;
#ifdef STATIC_GROUP
    int row = instance * ROW_TEXELS;
#else
    int row = (world * capacity + instance) * ROW_TEXELS;
#endif
    vec3 position = texelFetch(instances, row + ROW_POSITION).ROW_POSITION_LANES;
    vec4 rotation = texelFetch(instances, row + ROW_ROTATION).ROW_ROTATION_LANES;
    vec3 scale = max(texelFetch(instances, row + ROW_SCALE).ROW_SCALE_LANES, vec3(1e-6));
    v_color = texelFetch(instances, row + ROW_COLOR).ROW_COLOR_LANES;
#ifdef EFFECT_APPEARANCE
    // As batch.vert for an instance without a role: the world's colour transform and light.
    int look = world * APPEARANCE_TEXELS;
    vec3 terms = vec3(texelFetch(appearance, look + APPEARANCE_TRANSFORM_A).APPEARANCE_TRANSFORM_A_LANES,
                      texelFetch(appearance, look + APPEARANCE_TRANSFORM_B).APPEARANCE_TRANSFORM_B_LANES,
                      texelFetch(appearance, look + APPEARANCE_TRANSFORM_C).APPEARANCE_TRANSFORM_C_LANES);
    vec3 own = v_color.rgb;
    v_color.rgb = clamp(terms.x * own + terms.y * ((own.r + own.g + own.b) / 3.0)
                        + terms.z * (own.zxy - own.yzx), 0.0, 1.0);
#ifdef EFFECT_LIGHTING
    v_look_light_direction = texelFetch(appearance, look + APPEARANCE_LIGHT_DIRECTION).APPEARANCE_LIGHT_DIRECTION_LANES;
    v_look_light_color = texelFetch(appearance, look + APPEARANCE_LIGHT_COLOR).APPEARANCE_LIGHT_COLOR_LANES;
    v_look_ambient = texelFetch(appearance, look + APPEARANCE_AMBIENT).APPEARANCE_AMBIENT_LANES;
#endif
#endif

    int vrow = view * VIEW_TEXELS;
    int prow = vrow + VIEW_PROJECTION;
    mat4 view_projection = mat4(texelFetch(views, prow), texelFetch(views, prow + 1),
                                texelFetch(views, prow + 2), texelFetch(views, prow + 3));
#ifdef STATIC_GROUP
    vec3 relative = (position - texelFetch(views, vrow + VIEW_ORIGIN_HI).VIEW_ORIGIN_HI_LANES)
                  + (texelFetch(instances, row + ROW_POSITION_LO).ROW_POSITION_LO_LANES
                     - texelFetch(views, vrow + VIEW_ORIGIN_LO).VIEW_ORIGIN_LO_LANES);
#else
    vec3 relative = position;
#endif
    // Rows of the view-projection (GLSL matrices are indexed by column).
    vec4 row_x = vec4(view_projection[0][0], view_projection[1][0], view_projection[2][0], view_projection[3][0]);
    vec4 row_y = vec4(view_projection[0][1], view_projection[1][1], view_projection[2][1], view_projection[3][1]);
    vec4 row_z = vec4(view_projection[0][2], view_projection[1][2], view_projection[2][2], view_projection[3][2]);
    vec4 row_w = vec4(view_projection[0][3], view_projection[1][3], view_projection[2][3], view_projection[3][3]);
    // The camera is the point that clip x, y and w all put at 0.
    mat3 xyw = transpose(mat3(row_x.xyz, row_y.xyz, row_w.xyz));
    vec3 camera = inverse(xyw) * -vec3(row_x.w, row_y.w, row_w.w);

    vec4 inverse_rotation = vec4(rotation.x, -rotation.yzw);
    vec3 eye = rotate(inverse_rotation, camera - relative) / scale;
    // clip z and w of a point p of the instance's frame, world = relative + R (S p).
    v_clip_z = vec4(scale * rotate(inverse_rotation, row_z.xyz), dot(row_z.xyz, relative) + row_z.w);
    v_clip_w = vec4(scale * rotate(inverse_rotation, row_w.xyz), dot(row_w.xyz, relative) + row_w.w);
    v_eye = eye;

    // The rays from the eye that meet the sphere cross the plane of its silhouette (at RADIUS^2 / d
    // from the centre towards the eye) inside the silhouette circle (radius RADIUS sqrt(d^2 - RADIUS^2) / d):
    // the quad is the square around that circle.
    float d = length(eye);
    vec3 toward = eye / d;
    vec3 helper = abs(toward.z) < 0.9 ? vec3(0.0, 0.0, 1.0) : vec3(1.0, 0.0, 0.0);
    vec3 u = normalize(cross(helper, toward));
    vec3 v = cross(toward, u);
    float half_side = RADIUS * sqrt(max(d * d - RADIUS * RADIUS, 0.0)) / d;
    vec3 quad = toward * (RADIUS * RADIUS / d) + half_side * (p3d_Vertex.x * u + p3d_Vertex.y * v);
    v_quad = quad;
    vec4 clip = view_projection * vec4(relative + rotate(rotation, scale * quad), 1.0);
    if (d <= RADIUS || drawn >= pair_count) {
        // The camera is inside (nothing to draw: as a mesh, culled faces), or a quad past the pass's pairs.
        clip = vec4(0.0, 0.0, 2.0, 1.0);
    }

#ifdef LAYERED_VIEWS
    // batch.vert's layered placement: its own layer, at the same window coordinates in every layer.
    gl_Layer = pass_view;
    gl_Position = vec4(clip.x, -clip.y, clip.z, clip.w);
#else
    // The tile placement of batch.vert: clipped to this view's frustum, then moved into its tile
    // (flipped vertically: GL reads back bottom-up).
    gl_ClipDistance[0] = clip.w + clip.y;
    gl_ClipDistance[1] = clip.w - clip.y;
    gl_Position = vec4(clip.x, (float(2 * pass_view + 1 - tiles) * clip.w - clip.y) / float(tiles), clip.z, clip.w);
#endif

#ifdef EFFECT_LIGHTING
    v_rotation = rotation;
    v_inverse_scale = 1.0 / scale;
#endif
#ifdef OUTPUT_SEGMENTATION
    v_segment = segment_base + instance;
#endif
#ifdef LOG_DEPTH
    v_near_far = vec2(texelFetch(views, vrow + VIEW_NEAR).VIEW_NEAR_LANES,
                      texelFetch(views, vrow + VIEW_FAR).VIEW_FAR_LANES);
#endif
}
