#version 330 core
// Shadow-map pass, fragment stage: only the depth buffer is written.

void main()
{
}
