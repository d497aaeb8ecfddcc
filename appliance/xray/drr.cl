// Digitally reconstructed radiographs: rays from the focal spot through detector pixels.
//
// Volumes are int16 Hounsfield units, padded by PAD voxels of air on every side and laid
// out [k][j][i] (i fastest). All geometry arrives in padded voxel-index coordinates:
// voxel v spans [v - 0.5, v + 0.5] along each axis, the focal spot is `src`, and the ray
// of a pixel with normalised direction (x, y, 1) in the xray frame runs along A * (x, y, 1)
// with parameter t in units of the xray frame's z, so one unit of t is |(x, y, 1)| mm.
//
// geo (constant float[16]): A row-major (9), src (3), unused (4).
// box (constant int[8]): lo.xyz, pad, hi.xyz, pad: the voxels that can hold anything but
//   air, inclusive, in padded indices; rays are clipped to them.
// mat (constant float[8]): air_max_hu, bone_min_hu, contrast_min_hu, bone_offset,
//   bone_slope (g/cm^3 and g/cm^3 per HU); air and soft tissue follow 1 + HU/1000.
//
// No fast-math anywhere: results must not depend on the device's approximations.

#define PAD 2

inline float3 ray_dir(constant float *geo, float2 n)
{
    return (float3)(geo[0] * n.x + geo[1] * n.y + geo[2],
                    geo[3] * n.x + geo[4] * n.y + geo[5],
                    geo[6] * n.x + geo[7] * n.y + geo[8]);
}

// Clip src + t*d to the axis-aligned box [lo, hi]; false when it misses.
inline bool clip_box(float3 s, float3 d, float3 lo, float3 hi, float *t0, float *t1)
{
    float3 inv = (float3)(1.0f) / d;   // +-inf for an axis-parallel ray, handled by fmin/fmax
    float3 ta = (lo - s) * inv, tb = (hi - s) * inv;
    float3 tmin = fmin(ta, tb), tmax = fmax(ta, tb);
    // A ray parallel to an axis and outside the slab gives NaN or an empty range.
    if (d.x == 0.0f) { if (s.x < lo.x || s.x > hi.x) return false; tmin.x = -INFINITY; tmax.x = INFINITY; }
    if (d.y == 0.0f) { if (s.y < lo.y || s.y > hi.y) return false; tmin.y = -INFINITY; tmax.y = INFINITY; }
    if (d.z == 0.0f) { if (s.z < lo.z || s.z > hi.z) return false; tmin.z = -INFINITY; tmax.z = INFINITY; }
    *t0 = fmax(fmax(tmin.x, tmin.y), fmax(tmin.z, 0.0f));
    *t1 = fmin(fmin(tmax.x, tmax.y), tmax.z);
    return *t1 > *t0;
}

// Joseph's method: one bilinear sample per slice along the ray's dominant axis, the HU
// interpolated then split into materials. out[p] = integral of each material's density
// along the ray (g/cm^3 * mm), as float4 (air, soft tissue, bone, contrast).
kernel void joseph_materials(global const short *vol,
#ifdef BLEND
                             global const short *vol_b, const float w_b,
#endif
                             const int nx, const int ny, const int nz,
                             global const float2 *dirs, global const uchar *mask,
                             constant float *geo, constant int *box, constant float *mat,
                             global float4 *out)
{
    const int u = get_global_id(0), v = get_global_id(1);
    const int cols = get_global_size(0);
    const int p = v * cols + u;
    float4 acc = (float4)(0.0f);
    if (!mask[p]) { out[p] = acc; return; }
    const float2 n = dirs[p];
    const float3 d = ray_dir(geo, n);
    const float3 s = (float3)(geo[9], geo[10], geo[11]);
    const float mm_per_t = sqrt(n.x * n.x + n.y * n.y + 1.0f);
    // Samples bilinearly blend a slice's neighbours, so a voxel reaches one index beyond
    // itself in the in-slice axes: clip to the content box grown by one voxel.
    const float3 lo = (float3)(box[0], box[1], box[2]) - 1.0f;
    const float3 hi = (float3)(box[4], box[5], box[6]) + 1.0f;
    float t0, t1;
    if (!clip_box(s, d, lo, hi, &t0, &t1)) { out[p] = acc; return; }

    const float3 ad = fabs(d);
    int a, b, c;           // dominant axis a, in-slice axes b and c
    if (ad.x >= ad.y && ad.x >= ad.z) { a = 0; b = 1; c = 2; }
    else if (ad.y >= ad.z)            { a = 1; b = 0; c = 2; }
    else                              { a = 2; b = 0; c = 1; }
    const float sv[3] = {s.x, s.y, s.z};
    const float dv[3] = {d.x, d.y, d.z};
    const int stride[3] = {1, nx, nx * ny};
    const int lo_i[3] = {box[0], box[1], box[2]};
    const int hi_i[3] = {box[4], box[5], box[6]};

    // Slices k with the plane index_a = k between t0 and t1, inside the content box.
    const float a0 = sv[a] + t0 * dv[a], a1 = sv[a] + t1 * dv[a];
    int k0 = (int)ceil(fmin(a0, a1)), k1 = (int)floor(fmax(a0, a1));
    k0 = max(k0, lo_i[a]);
    k1 = min(k1, hi_i[a]);
    // Per slice step in the in-slice axes, and mm of ray per slice.
    const float inv_da = 1.0f / dv[a];
    const float db = dv[b] * inv_da, dc = dv[c] * inv_da;
    const float b0 = sv[b] - sv[a] * db, c0 = sv[c] - sv[a] * dc;
    const float step_mm = fabs(inv_da) * mm_per_t;
    const int sa = stride[a], sb = stride[b], sc = stride[c];
    const float air_max = mat[0], bone_min = mat[1], con_min = mat[2];
    const float bone_off = mat[3], bone_slope = mat[4];
    // In-slice coordinates stay inside the padding: clamp guards float rounding at the edges.
    const float bmax = (float)((b == 0 ? nx : ny) - 2), cmax = (float)((c == 1 ? ny : nz) - 2);

    for (int k = k0; k <= k1; ++k) {
        const float fbv = clamp(b0 + (float)k * db, 0.0f, bmax);
        const float fcv = clamp(c0 + (float)k * dc, 0.0f, cmax);
        const int ib = (int)fbv, ic = (int)fcv;
        const float wb = fbv - (float)ib, wc = fcv - (float)ic;
        const int base = k * sa + ib * sb + ic * sc;
        float h0 = mix((float)vol[base], (float)vol[base + sb], wb);
        float h1 = mix((float)vol[base + sc], (float)vol[base + sb + sc], wb);
        float h = mix(h0, h1, wc);
#ifdef BLEND
        h0 = mix((float)vol_b[base], (float)vol_b[base + sb], wb);
        h1 = mix((float)vol_b[base + sc], (float)vol_b[base + sb + sc], wb);
        h = mix(h, mix(h0, h1, wc), w_b);
#endif
        const float rho_w = fmax(1.0f + 0.001f * h, 0.0f);
        const bool is_air = h <= air_max, is_bone = h >= bone_min, is_con = h >= con_min;
        acc.x += is_air ? rho_w : 0.0f;
        acc.y += (!is_air && !is_bone) ? rho_w : 0.0f;
        acc.z += (is_bone && !is_con) ? bone_off + bone_slope * h : 0.0f;
        acc.w += is_con ? 1.0f : 0.0f;
    }
    out[p] = acc * step_mm;
}

// Energy-integrating detector: I/I0 = sum_e w_e exp(-sum_m mu_rho[e][m] * L_m), with L in
// g/cm^3 * mm (hence the 0.1 to g/cm^2) and w_e = N0(E) E normalised to sum 1. Pixels
// outside the mask read 0 (no signal).
kernel void polychromatic(global const float4 *lines, global const uchar *mask,
                          constant float *weights, constant float4 *mu_rho, const int n_e,
                          global float *out)
{
    const int p = get_global_id(0);
    if (!mask[p]) { out[p] = 0.0f; return; }
    const float4 L = lines[p] * 0.1f;
    float sum = 0.0f;
    for (int e = 0; e < n_e; ++e)
        sum += weights[e] * exp(-dot(mu_rho[e], L));
    out[p] = sum;
}

// Exact path lengths (Siddon, incremental as Amanatides and Woo): the integral of
// max(0, 1 + HU/1000) along the ray, in mm; multiplied by mu_water it is the line integral
// of mu = mu_water (1 + HU/1000) clipped at 0. Voxels are constant, not interpolated.
kernel void siddon_water(global const short *vol, const int nx, const int ny, const int nz,
                         global const float2 *dirs, global const uchar *mask,
                         constant float *geo, constant int *box, global float *out)
{
    const int u = get_global_id(0), v = get_global_id(1);
    const int p = v * get_global_size(0) + u;
    out[p] = 0.0f;
    if (!mask[p]) return;
    const float2 n = dirs[p];
    const float3 d = ray_dir(geo, n);
    const float3 s = (float3)(geo[9], geo[10], geo[11]);
    const float mm_per_t = sqrt(n.x * n.x + n.y * n.y + 1.0f);
    const int3 lo = (int3)(box[0], box[1], box[2]), hi = (int3)(box[4], box[5], box[6]);
    float t0, t1;
    if (!clip_box(s, d, convert_float3(lo) - 0.5f, convert_float3(hi) + 0.5f, &t0, &t1)) return;

    // The voxel at the midpoint of the first step is the entry voxel; boundaries follow.
    const float3 pin = s + t0 * d;
    int3 idx = clamp(convert_int3_rtn(pin + 0.5f), lo, hi);
    const int3 step = (int3)(d.x > 0 ? 1 : -1, d.y > 0 ? 1 : -1, d.z > 0 ? 1 : -1);
    const float3 inv = (float3)(1.0f) / d;
    float3 tnext = (convert_float3(idx) + 0.5f * convert_float3(step) - s) * inv;
    const float3 tdelta = fabs(inv);
    if (d.x == 0.0f) tnext.x = INFINITY;
    if (d.y == 0.0f) tnext.y = INFINITY;
    if (d.z == 0.0f) tnext.z = INFINITY;

    float t = t0, acc = 0.0f;
    while (t < t1) {
        const float te = fmin(fmin(fmin(tnext.x, tnext.y), tnext.z), t1);
        const float h = (float)vol[(idx.z * ny + idx.y) * nx + idx.x];
        acc += fmax(1.0f + 0.001f * h, 0.0f) * (te - t);
        t = te;
        if (tnext.x <= tnext.y && tnext.x <= tnext.z) { idx.x += step.x; tnext.x += tdelta.x; if (idx.x < lo.x || idx.x > hi.x) break; }
        else if (tnext.y <= tnext.z)                  { idx.y += step.y; tnext.y += tdelta.y; if (idx.y < lo.y || idx.y > hi.y) break; }
        else                                          { idx.z += step.z; tnext.z += tdelta.z; if (idx.z < lo.z || idx.z > hi.z) break; }
    }
    out[p] = acc * mm_per_t;
}
