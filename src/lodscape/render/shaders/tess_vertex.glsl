#version 410
in vec3 in_patch;        // u, v over the tile (0..1, v from the north), skirt flag
out vec3 c_patch;
void main() { c_patch = in_patch; }
