// The sky's colour, and the aux outputs' background values (the same as their clear values:
// depth +inf, segment 0), since a fragment writes every attachment.
flat in vec3 v_sky;

layout(location = 0) out vec4 out_color;
#ifdef OUTPUT_DEPTH
layout(location = DEPTH_LOCATION) out vec4 out_depth;
#endif
#ifdef OUTPUT_SEGMENTATION
layout(location = SEGMENTATION_LOCATION) out vec4 out_segment;
#endif

void main() {
#ifdef OUTPUT_GRAY
    out_color = vec4(vec3(dot(v_sky, vec3(0.299, 0.587, 0.114))), 1.0);  // shaders.GRAY_WEIGHTS
#else
    out_color = vec4(v_sky, 1.0);
#endif
#ifdef OUTPUT_DEPTH
    out_depth = unpackUnorm4x8(0x7f800000u);  // the bytes of +inf, least significant first
#endif
#ifdef OUTPUT_SEGMENTATION
    out_segment = vec4(0.0);
#endif
}
