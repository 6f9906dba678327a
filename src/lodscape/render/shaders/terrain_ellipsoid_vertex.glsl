#version 330
void main() {
    // one triangle over the whole viewport
    vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
    gl_Position = vec4(p, 1.0, 1.0);   // the far plane: only where nothing was drawn
}
