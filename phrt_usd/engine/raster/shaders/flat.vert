#version 330 core
// Id pass, vertex stage (loaded by pyrender's ShaderProgramCache for RenderFlags.FLAT).
//
// position: origin-relative world metres (Scene.origin subtracted, float32).
// M: model matrix (identity: all geometry is one node already in origin-relative world
// space); V: origin-relative world -> camera; P: camera -> clip.
// pyrender also binds a per-instance matrix at INST_M_LOC; we draw one instance whose
// matrix is the identity, so it is not read here.

layout(location = 0) in vec3 position;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;

void main()
{
    gl_Position = P * V * M * vec4(position, 1.0);
}
