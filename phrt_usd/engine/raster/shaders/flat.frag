#version 330 core
// Id pass, fragment stage: writes (triangle index + 1) as four exact bytes
// (R = least significant), so 0 is the background (cleared to 0) and ids up to
// 2^32 - 2 survive an RGBA8 buffer. No lighting, no gamma, no blending: the
// buffer is single-sampled and the value is an integer k / 255 that the UNORM
// conversion rounds back to k exactly.

out vec4 frag_color;

void main()
{
    uint id = uint(gl_PrimitiveID) + 1u;
    frag_color = vec4(
        float(id & 255u),
        float((id >> 8) & 255u),
        float((id >> 16) & 255u),
        float((id >> 24) & 255u)
    ) / 255.0;
}
