#ifdef LAYERED_VIEWS
// Every view is drawn into its own layer of an array texture (BatchRenderer(layered=True)).
#extension GL_ARB_shader_viewport_layer_array : require
#endif
// One instanced draw covers every view of every world. Instance k of the draw is the
// k-th visible (view, instance) pair of this pass, listed by the renderer after
// frustum culling in torch; pairs are sorted by view.
// Effects and group kinds arrive as #defines prepended by marl_render/shaders.py, and so
// does the buffer layout: ROW_<FIELD> / VIEW_<FIELD> is a field's texel in its row and
// ROW_<FIELD>_LANES its swizzle, generated from the table in marl_render/layout.py.
in vec4 p3d_Vertex;
in vec3 p3d_Normal;
#ifdef EFFECT_TEXTURE
in vec2 p3d_MultiTexCoord0;
out vec2 v_uv;
#endif
#ifdef SKINNING
in vec4 skin_joints;   // up to four joint indices per vertex (stored as floats), heaviest first
in vec4 skin_weights;  // their weights, summing to 1 over the first SKIN_INFLUENCES
#endif

uniform samplerBuffer instances;  // ROW_TEXELS texels per instance (rows: marl_render/layout.py)
uniform samplerBuffer views;      // VIEW_TEXELS texels per view
uniform isamplerBuffer pairs;     // view * capacity + instance, visible pairs only
uniform int pair_offset;          // first pair of this pass
uniform int capacity;             // instances per world in this group
uniform int agents;               // views per world
uniform int view_offset;          // first view drawn by this pass
uniform int tiles;                // tiles per pass, stacked in one column
#ifdef SHADOW_CASTER
uniform ivec2 grid;               // shadow atlas: (tiles per row, tile rows), one square tile per world
#endif
uniform int segment_base;         // segmentation id of this group's instance 0

// One colour per triangle, taken from its provoking (last) vertex: an instance's colour,
// lit per vertex only on flat meshes, whose triangles have one normal each (at the
// provoking vertex when the mesh is drawn from its shared corners, provoking.py). Flat,
// because interpolating a constant is not exact and its rounding would depend on where
// the tile sits.
flat out vec4 v_color;
#ifdef LIGHT_PER_FRAGMENT
out vec3 v_normal;
#endif
#if defined(LIGHT_PER_VERTEX) && !defined(EFFECT_APPEARANCE)
uniform vec3 light_direction;  // world frame, pointing from the light
uniform vec3 light_color;
uniform vec3 ambient_color;
#endif
#ifdef EFFECT_APPEARANCE
// Each world's look (rows: APPEARANCE_* from marl_render/layout.py): its light, the colours and
// patterns of floors and walls, the colour transform of everything else.
uniform samplerBuffer appearance;
#ifdef LIGHT_PER_FRAGMENT
flat out vec3 v_look_light_direction;  // the world's light, for the fragment stage
flat out vec3 v_look_light_color;
flat out vec3 v_look_ambient;
#endif
#ifdef APPEARANCE_SURFACE
// A floor's or wall's pattern coordinates (cells) at the vertex; its pattern's shift along u per row
// of cells (bricks) travels in v_color.a, which the fragment stage has no other use for (one flat
// input fewer: llvmpipe sets up and loads each input per block of pixels).
out vec2 v_surface;
flat out vec4 v_pattern;  // the factors its pattern leaves past the line threshold along u, v, both; the threshold
#endif
#endif
#if defined(EFFECT_FOG) || defined(OUTPUT_DEPTH) || defined(LOG_DEPTH)
out float v_depth;
#endif
#ifdef LOG_DEPTH
flat out vec2 v_near_far;
#endif
#ifdef EXACT_TILES
// exact.geom clips each triangle in this view's clip space, moves it into its tile and hands the
// fragment stage its planes: this stage stays in the view's clip space.
uniform vec2 tile_size;       // (width, height) of a tile in pixels
flat out float v_tile_row;    // the first window row of the view's tile
#elif defined(OUTPUT_DEPTH)
// Depth comes from each triangle's plane (see batch.frag).
uniform vec2 tile_size;       // pixels
#ifdef DEPTH_PLANE_FROM_CORNERS
// This vertex is the provoking (last) vertex of at most one triangle and carries that
// triangle's two other corners (marl_render/triangle_corners.py).
in vec3 corner_a;
in vec3 corner_b;
flat out vec4 depth_plane;    // n.(x, y, w) = d in the view's clip space
flat out vec4 depth_tile;     // tile origin (pixels), smallest and largest w of the triangle
#else
// For the geometry shader (batch.geom), which has the whole triangle (model files, skinned meshes).
out vec3 v_clip;              // (x, y, w) before the move into the tile
flat out vec2 v_tile_origin;  // pixel of the tile's lower-left corner (window coordinates)
#ifdef LAYERED_VIEWS
flat out int v_layer;
#endif
#endif
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
flat out vec3 v_direct;        // the directional light's share of the (flat) colour, dimmed per fragment
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
    int row = instance * ROW_TEXELS;      // shared by all worlds
#else
    int row = (world * capacity + instance) * ROW_TEXELS;
#endif
    vec3 position = texelFetch(instances, row + ROW_POSITION).ROW_POSITION_LANES;
    vec4 rotation = texelFetch(instances, row + ROW_ROTATION).ROW_ROTATION_LANES;  // unit (w, x, y, z)
    vec3 scale = texelFetch(instances, row + ROW_SCALE).ROW_SCALE_LANES;
    v_color = texelFetch(instances, row + ROW_COLOR).ROW_COLOR_LANES;
#ifdef EFFECT_APPEARANCE
    int look = world * APPEARANCE_TEXELS;
#ifdef STATIC_GROUP
    int role = int(texelFetch(instances, row + ROW_ROLE).ROW_ROLE_LANES + 0.5);  // per instance
#elif defined(GROUP_ROLE)
    int role = GROUP_ROLE;
#else
    int role = 0;
#endif
    // Fetched before any branch: they share their texels with the light, which the compiler then
    // fetches once.
    vec3 terms = vec3(texelFetch(appearance, look + APPEARANCE_TRANSFORM_A).APPEARANCE_TRANSFORM_A_LANES,
                      texelFetch(appearance, look + APPEARANCE_TRANSFORM_B).APPEARANCE_TRANSFORM_B_LANES,
                      texelFetch(appearance, look + APPEARANCE_TRANSFORM_C).APPEARANCE_TRANSFORM_C_LANES);
#ifdef APPEARANCE_SURFACE
    vec4 cells = vec4(0.0);  // (cells per metre along u and v, shift, threshold) of a floor or wall
    v_pattern = vec4(1.0);   // no role: nothing past a threshold of 1, and every factor 1
#endif
    if (role == 0) {
        // Not a floor or wall: the world's colour transform (hue, saturation and value jitter),
        // a rgb + b mean(rgb) + c ((1, 1, 1) x rgb), a rotation about the grey axis and scalings.
        vec3 own = v_color.rgb;
        v_color.rgb = clamp(terms.x * own + terms.y * ((own.r + own.g + own.b) / 3.0)
                            + terms.z * (own.zxy - own.yzx), 0.0, 1.0);
    } else {
        bool floor_role = role == 1;
        vec4 surface = texelFetch(appearance, look + (floor_role ? APPEARANCE_FLOOR : APPEARANCE_WALL));
        v_color.rgb = surface.w > 0.5 ? surface.rgb : v_color.rgb;  // w 0: the instance's own colour
#ifdef APPEARANCE_SURFACE
        int pattern = look + (floor_role ? APPEARANCE_FLOOR_PATTERN : APPEARANCE_WALL_PATTERN);
        cells = texelFetch(appearance, pattern);
        v_pattern = vec4(texelFetch(appearance, pattern + 1).xyz, cells.w);
#endif
    }
#ifdef EFFECT_LIGHTING
    vec3 light_direction = texelFetch(appearance, look + APPEARANCE_LIGHT_DIRECTION).APPEARANCE_LIGHT_DIRECTION_LANES;
    vec3 light_color = texelFetch(appearance, look + APPEARANCE_LIGHT_COLOR).APPEARANCE_LIGHT_COLOR_LANES;
    vec3 ambient_color = texelFetch(appearance, look + APPEARANCE_AMBIENT).APPEARANCE_AMBIENT_LANES;
#ifdef LIGHT_PER_FRAGMENT
    v_look_light_direction = light_direction;
    v_look_light_color = light_color;
    v_look_ambient = ambient_color;
#endif
#endif
#endif

    vec3 vertex = p3d_Vertex.xyz;
#ifdef EFFECT_LIGHTING
    vec3 vertex_normal = p3d_Normal;
#endif
#ifdef SKINNING
    // Linear-blend skinning: blend the 3x4 bind-to-pose matrices of the vertex's joints
    // (JOINT_TEXELS rows each, after the instance's own texels), then apply it once. The
    // mesh's vertices follow at most SKIN_INFLUENCES joints: texel fetches are the cost.
    vec4 blend0 = vec4(0.0), blend1 = vec4(0.0), blend2 = vec4(0.0);
    for (int k = 0; k < SKIN_INFLUENCES; ++k) {
        int joint_row = row + FIRST_JOINT_TEXEL + JOINT_TEXELS * int(skin_joints[k] + 0.5);
        blend0 += skin_weights[k] * texelFetch(instances, joint_row);
        blend1 += skin_weights[k] * texelFetch(instances, joint_row + 1);
        blend2 += skin_weights[k] * texelFetch(instances, joint_row + 2);
    }
    vertex = vec3(dot(blend0, vec4(vertex, 1.0)), dot(blend1, vec4(vertex, 1.0)), dot(blend2, vec4(vertex, 1.0)));
#ifdef EFFECT_LIGHTING
    vertex_normal = vec3(dot(blend0.xyz, vertex_normal), dot(blend1.xyz, vertex_normal), dot(blend2.xyz, vertex_normal));
#endif
#endif

    int vrow = view * VIEW_TEXELS;
    int prow = vrow + VIEW_PROJECTION;  // four texels, one column each
    mat4 view_projection = mat4(texelFetch(views, prow), texelFetch(views, prow + 1),
                                texelFetch(views, prow + 2), texelFetch(views, prow + 3));
#ifdef STATIC_GROUP
    // Positions relative to the world's origin in two floats each (hi + lo), so that
    // scenes far from 0 keep sub-millimetre precision.
    vec3 relative = (position - texelFetch(views, vrow + VIEW_ORIGIN_HI).VIEW_ORIGIN_HI_LANES)
                  + (texelFetch(instances, row + ROW_POSITION_LO).ROW_POSITION_LO_LANES
                     - texelFetch(views, vrow + VIEW_ORIGIN_LO).VIEW_ORIGIN_LO_LANES);
#else
    vec3 relative = position;  // already relative to the world's origin
#endif
    vec3 world_position = relative + rotate(rotation, vertex * scale);
#ifdef APPEARANCE_SURFACE
    // Floors are patterned in (x, y); walls along the wall (x + y: an axis-aligned wall has one
    // of them constant) and up. Linear in the position, so interpolating it is exact.
    v_surface = (role == 1 ? world_position.xy : vec2(world_position.x + world_position.y, world_position.z))
              * cells.xy;
    v_color.a = cells.z;
#endif
    vec4 clip = view_projection * vec4(world_position, 1.0);

#if defined(EXACT_TILES) && !defined(SHADOW_CASTER)
    gl_Position = clip;  // exact.geom clips it and moves it into its tile
    v_tile_row = float(pass_view) * tile_size.y;
#elif defined(LAYERED_VIEWS) && !defined(SHADOW_CASTER)
    // Its own layer, at the same window coordinates as every other view: no tile offset, so
    // llvmpipe's snapping, clipping and interpolation see the same numbers in every layer.
    // Flipped vertically like the tiles (GL reads back bottom-up).
    gl_Layer = pass_view;
#ifdef DEPTH_PLANE_FROM_GEOMETRY
    v_layer = pass_view;  // a geometry stage must write gl_Layer itself
#endif
    gl_Position = vec4(clip.x, -clip.y, clip.z, clip.w);
#else
    // Clip against this view's own frustum before moving it into its tile, so nothing
    // spills into a neighbour. Tiles span the framebuffer's width (one column), so the
    // viewport clips x; only the top and bottom need planes.
    gl_ClipDistance[0] = clip.w + clip.y;
    gl_ClipDistance[1] = clip.w - clip.y;

#ifdef SHADOW_CASTER
    // The shadow atlas is a near-square grid of tiles (one texture holds every world's
    // map, shadows.py), so the sides need planes too. Flipped like the views.
    gl_ClipDistance[2] = clip.w + clip.x;
    gl_ClipDistance[3] = clip.w - clip.x;
    ivec2 tile = ivec2(pass_view % grid.x, pass_view / grid.x);
    vec2 tile_shift = vec2(2 * tile + 1 - grid);
    gl_Position = vec4((vec2(clip.x, -clip.y) + clip.w * tile_shift) / vec2(grid), clip.z, clip.w);
#else
    // Tiles are stored top row first in memory (GL reads back bottom-up), so each view is
    // flipped vertically; the renderer flips the cull mode to match.
    gl_Position = vec4(clip.x, (float(2 * pass_view + 1 - tiles) * clip.w - clip.y) / float(tiles), clip.z, clip.w);
#endif
#endif

#ifdef EFFECT_LIGHTING
    // Normals scale inversely (inverse transpose); a zero scale flattens the mesh, and
    // the normal then points straight out of the flat side.
    vec3 normal = rotate(rotation, normalize(vertex_normal / max(scale, vec3(1e-6))));
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
    int lrow = world * VIEW_TEXELS + VIEW_PROJECTION;
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
#if defined(OUTPUT_DEPTH) && !defined(EXACT_TILES)
    // Tile t of the column covers window rows [t * H, (t + 1) * H) from the bottom.
#ifdef LAYERED_VIEWS
    vec2 tile_origin = vec2(0.0);  // every layer starts at window (0, 0)
#else
    vec2 tile_origin = vec2(0.0, float(pass_view)) * tile_size;
#endif
#ifdef DEPTH_PLANE_FROM_CORNERS
    vec3 q0 = (view_projection * vec4(relative + rotate(rotation, corner_a * scale), 1.0)).xyw;
    vec3 q1 = (view_projection * vec4(relative + rotate(rotation, corner_b * scale), 1.0)).xyw;
    vec3 q2 = clip.xyw;
    vec3 plane_normal = cross(q1 - q0, q2 - q0);
    depth_plane = vec4(plane_normal, dot(plane_normal, q0));
    depth_tile = vec4(tile_origin, min(q0.z, min(q1.z, q2.z)), max(q0.z, max(q1.z, q2.z)));
#else
    v_clip = clip.xyw;
    v_tile_origin = tile_origin;
#endif
#endif
#ifdef LOG_DEPTH
    v_near_far = vec2(texelFetch(views, vrow + VIEW_NEAR).VIEW_NEAR_LANES,
                      texelFetch(views, vrow + VIEW_FAR).VIEW_FAR_LANES);
#endif
#ifdef OUTPUT_SEGMENTATION
    v_segment = segment_base + instance;
#endif
}
