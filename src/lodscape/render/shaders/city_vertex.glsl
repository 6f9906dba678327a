#version 330
#ifdef BLOCKS
// the frame's camera in one uniform buffer, written once a frame for every program
layout(std140) uniform Frame { mat4 f_mvp; mat4 f_rot; vec4 f_offset; vec4 f_sun; };
#define MVP f_mvp
#define ROT mat3(f_rot)
#define OFFSET f_offset.xyz
#else
uniform mat4 u_mvp;      // projection · view for positions in the city's frame
uniform mat3 u_rot;      // city frame → view rotation
uniform vec3 u_offset;   // view-space position of the city's origin
#define MVP u_mvp
#define ROT u_rot
#define OFFSET u_offset
#endif
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
#ifdef INSTANCED
#ifdef BLOCKS
// per instance x, y, z, scale, heading (five floats), read by the draw's base instance
layout(std430, binding = 1) readonly buffer Instances { float inst[]; };
#else
in vec4 in_inst;         // x, y, z, scale
in float in_heading;
#endif
#endif
out vec3 v_normal;
out vec2 v_uv;
out float v_dist;
out vec3 v_view;         // view space: the label pass's normal and its facing
out vec3 v_view_normal;
void main() {
    vec3 p = in_pos;
    vec3 n = in_normal;
#ifdef INSTANCED
#ifdef BLOCKS
    int i = 5 * (gl_BaseInstanceARB + gl_InstanceID);
    vec4 in_inst = vec4(inst[i], inst[i + 1], inst[i + 2], inst[i + 3]);
    float in_heading = inst[i + 4];
#endif
    float c = cos(in_heading), s = sin(in_heading);
    mat3 r = mat3(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0);
    p = in_inst.xyz + r * (in_inst.w * p);
    n = r * n;
#endif
    gl_Position = MVP * vec4(p, 1.0);
    v_normal = n;
    v_uv = in_uv;
    v_view = OFFSET + ROT * p;
    v_view_normal = ROT * n;
    v_dist = -v_view.z;
}
