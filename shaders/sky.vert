// The sky of the "appearance" effect: each world's background colour. One quad per view of the
// pass (instance = view), drawn after everything else at the far plane with depth test LEQUAL and
// no depth write, so it shows only where nothing was drawn (the framebuffer's clear colour is one
// for all tiles). Tiles stack in one column, flipped vertically as in batch.vert.
in vec4 p3d_Vertex;  // the corners of meshes.plane(), x and y in [-0.5, 0.5]

uniform samplerBuffer appearance;  // APPEARANCE_TEXELS texels per world (marl_render/layout.py)
uniform int agents;                // views per world
uniform int view_offset;           // first view drawn by this pass
uniform int tiles;                 // tiles per pass

flat out vec3 v_sky;

void main() {
    int world = (view_offset + gl_InstanceID) / agents;
    v_sky = texelFetch(appearance, world * APPEARANCE_TEXELS + APPEARANCE_SKY).APPEARANCE_SKY_LANES;
    vec2 corner = 2.0 * p3d_Vertex.xy;  // the whole tile
    gl_Position = vec4(corner.x, (float(2 * gl_InstanceID + 1 - tiles) - corner.y) / float(tiles), 1.0, 1.0);
}
