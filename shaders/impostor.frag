// The sphere impostor's fragments (impostor.vert says what the quad is): the pixel's ray, from the
// camera through this point of the quad, meets the sphere of radius 0.5 in the instance's frame
// or the pixel is discarded. At the nearer hit: the depth the depth test compares (gl_FragDepth),
// the normal (the hit point itself, turned into the world frame with the inverse scale), and the
// same colour, lighting, fog and outputs as batch.frag.
flat in vec4 v_color;
in vec3 v_quad;
flat in vec3 v_eye;
flat in vec4 v_clip_z;
flat in vec4 v_clip_w;
#ifdef EFFECT_LIGHTING
flat in vec4 v_rotation;
flat in vec3 v_inverse_scale;
#ifdef EFFECT_APPEARANCE
flat in vec3 v_look_light_direction;
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
#ifdef EFFECT_FOG
uniform vec3 fog_color;
uniform float fog_density;
#endif
#ifdef LOG_DEPTH
flat in vec2 v_near_far;
#endif
#ifdef OUTPUT_SEGMENTATION
flat in int v_segment;
#endif

layout(location = 0) out vec4 out_color;
#ifdef OUTPUT_DEPTH
layout(location = DEPTH_LOCATION) out vec4 out_depth;
#endif
#ifdef OUTPUT_SEGMENTATION
layout(location = SEGMENTATION_LOCATION) out vec4 out_segment;
#endif

const float RADIUS = 0.5;

vec3 rotate(vec4 q, vec3 v) {
    vec3 t = 2.0 * cross(q.yzw, v);
    return v + q.x * t + cross(q.yzw, t);
}

void main() {
    // The ray's closest approach to the centre, then back along the ray to the surface: no
    // difference of two large squares (a small sphere seen from afar keeps its precision).
    vec3 direction = normalize(v_quad - v_eye);
    float along = -dot(v_eye, direction);
    vec3 closest = v_eye + along * direction;
    float inside = RADIUS * RADIUS - dot(closest, closest);
    if (inside < 0.0) {
        discard;
    }
    vec3 hit = closest - sqrt(inside) * direction;
    float clip_w = dot(v_clip_w, vec4(hit, 1.0));
    float depth_ndc = dot(v_clip_z, vec4(hit, 1.0)) / clip_w;
    if (abs(depth_ndc) > 1.0) {
        discard;  // outside the near and far planes, where a mesh would be clipped
    }
#ifdef LOG_DEPTH
    gl_FragDepth = log2(max(clip_w, v_near_far.x) / v_near_far.x) / log2(v_near_far.y / v_near_far.x);
#else
    gl_FragDepth = 0.5 * depth_ndc + 0.5;
#endif
    vec3 color = v_color.rgb;
#ifdef EFFECT_LIGHTING
    vec3 normal = normalize(rotate(v_rotation, hit * v_inverse_scale));
    color *= ambient_color + light_color * max(dot(normal, -light_direction), 0.0);
#endif
#ifdef EFFECT_FOG
    color = mix(fog_color, color, exp(-fog_density * clip_w));
#endif
#ifdef OUTPUT_GRAY
    out_color = vec4(vec3(dot(clamp(color, 0.0, 1.0), vec3(0.299, 0.587, 0.114))), 1.0);
#else
    out_color = vec4(clamp(color, 0.0, 1.0), 1.0);
#endif
#ifdef OUTPUT_DEPTH
    out_depth = unpackUnorm4x8(floatBitsToUint(clip_w));  // metres along the view axis, as batch.frag
#endif
#ifdef OUTPUT_SEGMENTATION
    out_segment = unpackUnorm4x8(uint(v_segment));
#endif
}
