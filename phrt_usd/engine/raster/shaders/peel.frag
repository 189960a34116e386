#version 330 core
// Cut-out id layers (cutout_layers.py), fragment stage: the id pass's encoding
// (flat.frag: id + 1 as four exact bytes, R least significant; keep the two in step,
// tests/engine/test_cutouts.py compares their ids) with depth peeling.
//
// id_base: offset of this draw's first triangle in the layer's id list (the static,
// then the animated triangles). When `peeling`, `previous` holds per pixel the layer
// before: R = its id (0: the pixel is not peeled, every fragment is discarded), G = its
// window depth's float bits. A fragment is kept only if it lies after that layer in
// the order (depth, id), so each layer is the next surface along the pixel's ray and
// coplanar surfaces are visited once each, in id order. No cut-out rule here: which
// pixels are holes is decided on the CPU (model/surface.py Cutouts).

uniform int id_base;
uniform int peeling;
uniform usampler2D previous;

out vec4 frag_color;

void main()
{
    uint id = uint(id_base) + uint(gl_PrimitiveID) + 1u;
    if (peeling != 0) {
        uvec2 prev = texelFetch(previous, ivec2(gl_FragCoord.xy), 0).rg;
        if (prev.r == 0u) {
            discard;
        }
        float prev_z = uintBitsToFloat(prev.g);
        float z = gl_FragCoord.z;
        if (z < prev_z || (z == prev_z && id <= prev.r)) {
            discard;
        }
    }
    frag_color = vec4(
        float(id & 255u),
        float((id >> 8) & 255u),
        float((id >> 16) & 255u),
        float((id >> 24) & 255u)
    ) / 255.0;
}
