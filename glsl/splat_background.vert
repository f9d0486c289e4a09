#version 450
// The draw path's last draw: one triangle over the whole image (splat_background.frag).
void main() {
    vec2 p = vec2((gl_VertexIndex & 1) != 0 ? 3.0 : -1.0, (gl_VertexIndex & 2) != 0 ? 3.0 : -1.0);
    gl_Position = vec4(p, 0.0, 1.0);
}
