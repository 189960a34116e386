#version 330 core
// Shadow-map pass, vertex stage.
//
// position: origin-relative world metres (float32).
// light_clip_from_world: origin-relative world -> the light's orthographic clip space.

layout(location = 0) in vec3 position;

uniform mat4 light_clip_from_world;

void main()
{
    gl_Position = light_clip_from_world * vec4(position, 1.0);
}
