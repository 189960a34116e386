#version 330 core
// LocalLight shadow lookups, vertex stage: one triangle covering the whole viewport
// (vertex ids 0, 1, 2 -> clip (-1, -1), (3, -1), (-1, 3)); no vertex attributes.

void main()
{
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
