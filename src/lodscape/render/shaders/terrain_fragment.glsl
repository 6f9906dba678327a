#version 330
uniform sampler2D u_tex;
uniform vec4 u_tint;     // the viewer's LOD colouring: a colour and how much of it
// imagery layers over the terrain's own texture, bottom to top, each with its own window; a
// program holds the code of as many as its scene has (LAYERS): a software rasteriser runs
// every branch a uniform would skip, and four layer lookups cost a fifth of a frame there
#ifndef LAYERS
#define LAYERS 4
#endif
uniform sampler2D u_layer0;
uniform sampler2D u_layer1;
uniform sampler2D u_layer2;
uniform sampler2D u_layer3;
uniform vec3 u_layer_uv[4];
uniform int u_layers;
in vec2 v_uv;
in vec2 v_tuv;           // where in the tile (0..1), for the layers' windows
in float v_dist;
in vec3 v_view;
#ifdef HEIGHT_NORMALS
in vec3 v_normal;        // view space, from the height texture
#endif
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_dist;
UNDERSIDE_GLSL
vec3 over(vec3 c, sampler2D s, vec3 w) {
    vec4 t = texture(s, w.xy + w.z * v_tuv);
    return mix(c, t.rgb, t.a);
}
void main() {
    // the imagery already carries its shading: no lighting here
    // alpha marks where the data covers the tile: the terrain ends at the data's edge. It is
    // read from the base level's nearest texel: mipmaps average it with the no-data around, and
    // a steep face seen edge-on (a coarse mip) would otherwise be cut open (textureLod does
    // the same but is pathologically slow on llvmpipe)
#ifndef WHOLE
    // (the WHOLE variant draws tiles whose texture has no such texel: no discard at all, so
    // the depth test may run before the shader)
    ivec2 size = textureSize(u_tex, 0);
    ivec2 texel = clamp(ivec2(floor(v_uv * vec2(size))), ivec2(0), size - 1);
    if (texelFetch(u_tex, texel, 0).a < 0.5) discard;
#endif
#ifdef LABELS
    if (drawn_apart(u_class_label[0])) return;
#else
    if (drawn_apart(0.0)) return;
#endif
    vec3 c = texture(u_tex, v_uv).rgb;
#if LAYERS > 0
    if (u_layers > 0) c = over(c, u_layer0, u_layer_uv[0]);
#endif
#if LAYERS > 1
    if (u_layers > 1) c = over(c, u_layer1, u_layer_uv[1]);
#endif
#if LAYERS > 2
    if (u_layers > 2) c = over(c, u_layer2, u_layer_uv[2]);
#endif
#if LAYERS > 3
    if (u_layers > 3) c = over(c, u_layer3, u_layer_uv[3]);
#endif
    f_color = vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
    f_dist = v_dist;
}
