#version 330 core
// Cut-out id layers (cutout_layers.py), vertex stage.
//
// position: origin-relative world metres (float32), the mesh's own vertex buffer.
// clip_from_rel: origin-relative world -> clip space of the view being peeled (a
// camera, a DistantLight's orthographic map, a cube-map face).

layout(location = 0) in vec3 position;

uniform mat4 clip_from_rel;

void main()
{
    gl_Position = clip_from_rel * vec4(position, 1.0);
}
