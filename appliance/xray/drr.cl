// Digitally reconstructed radiographs: rays from the focal spot through detector pixels.
//
// Volumes are int16 Hounsfield units, padded by PAD voxels of air on every side and laid
// out [k][j][i] (i fastest), or, a slab copy's (slab_axis >= 0, see slab_rows), with the rows of
// its slices along that dominant axis contiguous, whatever the axis (see LAYOUT). All geometry arrives in padded voxel-index coordinates:
// voxel v spans [v - 0.5, v + 0.5] along each axis, the focal spot is `src`, and the ray
// of a pixel with normalised direction (x, y, 1) in the xray frame runs along A * (x, y, 1)
// with parameter t in units of the xray frame's z, so one unit of t is |(x, y, 1)| mm.
//
// geo (constant float[16]): A row-major (9), src (3), edge (1), unused (3). edge > 0: the width
//   (display pixels) over which a Joseph sample passes from a voxel to its in-slice neighbour
//   where voxels are larger than that (see VOXEL_WEIGHT); 0: plain linear interpolation.
// box (constant int[8]): lo.xyz, pad, hi.xyz, pad: the voxels that can hold anything but
//   air, inclusive, in padded indices; rays are clipped to them.
// planes (constant float[1 + 5 n]): n, then per plane normal.xyz, lo, hi: the content's outline
//   (outline.py), lo <= normal . p <= hi already grown by how far a sample reaches; rays are
//   clipped to them too, inside the box (n = 0: the box alone).
// mat (constant float[8]): air_max_hu, bone_min_hu, contrast_min_hu, bone_offset,
//   bone_slope (g/cm^3 and g/cm^3 per HU); air and soft tissue follow 1 + HU/1000.
//
// No fast-math anywhere: results must not depend on the device's approximations.

#define PAD 2

// a b + c in one instruction where the device has a fused multiply-add (x86's FMA, GPUs): PoCL
// keeps mad() and mix() a multiply and an add, and they are most of a sample's arithmetic. fma()
// is exact (one rounding), not an approximation; where it would be emulated in software, which
// is slow, the two operations stay. Every kernel here uses the same, so they agree to the bit.
#if defined(__FMA__) || defined(FP_FAST_FMAF)
#define FMA(a, b, c) fma((a), (b), (c))
#else
#define FMA(a, b, c) ((a) * (b) + (c))
#endif

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

// Clip src + t*d further to the outline's planes (see `planes` above); false when it misses.
inline bool clip_planes(constant float *planes, float3 s, float3 d, float *t0, float *t1)
{
    const int n = (int)planes[0];
    for (int j = 0; j < n; ++j) {
        constant float *q = planes + 1 + 5 * j;
        const float ns = q[0] * s.x + q[1] * s.y + q[2] * s.z, nd = q[0] * d.x + q[1] * d.y + q[2] * d.z;
        if (nd == 0.0f) {               // parallel to the plane: inside it throughout, or never
            if (ns < q[3] || ns > q[4]) return false;
            continue;
        }
        const float ta = (q[3] - ns) / nd, tb = (q[4] - ns) / nd;
        *t0 = fmax(*t0, fmin(ta, tb));
        *t1 = fmin(*t1, fmax(ta, tb));
    }
    return *t1 > *t0;
}

// Where the CT's voxels are larger than the display pixel, linear interpolation between two
// voxel centres turns each voxel's edge into a ramp a whole voxel wide (a 2.5 mm slice seen
// through 0.24 mm pixels: a 10-pixel ramp), which the voxel grid does not have: its exact line
// integral (Siddon) steps there. The CT's voxels are piecewise constant; a detector pixel
// averages that over its footprint, so the sample's weight is the constant grid seen through a
// box `width` voxels wide: a ramp `width` wide centred on the voxels' shared face. The box is
// the pixel's footprint (times the profile's voxel_edge_px), or the ray's own travel across the
// axis in one Joseph step where that is wider (a ray steep to the slices: one sample stands for
// the whole step, whose exact integral over a face is a ramp that wide). At width 1 (a voxel
// no bigger than either) that is linear interpolation, which is kept there, untouched.
// VOXEL_WEIGHT(w, inv, off), inv = VOXEL_SLOPE(width) = 1 / min(width, 1), off = (1 - inv) / 2,
// maps the linear weight w in [0, 1) to that box's; BLOCKS(wanted): whether the weights get it
// (LINEAR_SAMPLES: never, the plain kernel `bench drr` times this sampling against). fmin(fmax()), not clamp(): PoCL's float16
// clamp made the packet kernel 10-20 % slower where these are single vector instructions.
#define VOXEL_SLOPE(width) (1.0f / fmin(fmax((width), 1e-3f), 1.0f))
#define VOXEL_WEIGHT(w, inv, off) fmin(fmax(FMA((w), (inv), (off)), 0.0f), 1.0f)
#ifdef LINEAR_SAMPLES
#define BLOCKS(wanted) false
#else
#define BLOCKS(wanted) (wanted)
#endif

// A sample's voxel (ib, ic) of slice k along the dominant axis a is at k * sa + ib * sb + ic * sc
// (shorts), its neighbours across b and c `sb` and `oc` further on. The plain layout [z][y][x]:
// the axes' strides. A slab copy along a (slab_rows): rows along b, then slices along a, then c,
// so that rays along a read rows along b (sb = 1) whatever a is (see ROWS).
#define LAYOUT(slab_axis, dims, a, b, c, sa, sb, sc, oc) do { \
    if ((slab_axis) < 0) { \
        const int st_[3] = {1, (dims)[0], (dims)[0] * (dims)[1]}; \
        sa = st_[a]; sb = st_[b]; sc = st_[c]; \
    } else { \
        sb = 1; sa = (dims)[b]; sc = sa * (dims)[a]; \
    } \
    oc = sc; } while (0)

// any() and all() of a packet's int16 masks (the packet kernels below). PoCL lowers the built-ins
// to a chain of sixteen extracts and branches, which took a quarter of a chest's cast in the
// Joseph loop; with AVX-512 (DQ) the comparison's own mask register answers in one instruction,
// with AVX the sign bits of each half's eight lanes in one each (movmskps). Elsewhere the
// built-ins, which give the same answer. (NO_MASK_REGISTERS leaves AVX-512's out, so that tests
// can check the AVX path on such a CPU too.)
#if defined(__AVX512F__)
// Sixteen ints as the AVX-512 builtins here and below take them.
typedef int v16si __attribute__((vector_size(64)));
#endif
#if defined(__AVX512DQ__) && !defined(NO_MASK_REGISTERS)
#define ANY16(m) (__builtin_ia32_cvtd2mask512(__builtin_astype((m), v16si)) != 0)
#define ALL16(m) (__builtin_ia32_cvtd2mask512(__builtin_astype((m), v16si)) == (ushort)0xffff)
#elif defined(__AVX__)
typedef float v8sf_m __attribute__((vector_size(32)));
#define SIGNS8(h) __builtin_ia32_movmskps256(__builtin_astype((h), v8sf_m))
#define SIGNS16(m) ({ const int16 m_ = (m); SIGNS8(m_.lo) | (SIGNS8(m_.hi) << 8); })
#define ANY16(m) (SIGNS16(m) != 0)
#define ALL16(m) (SIGNS16(m) == 0xffff)
#else
#define ANY16(m) any(m)
#define ALL16(m) all(m)
#endif

// One bilinear sample of the corner voxels g00..g11 (HU; in-slice weights wb, wc) into the
// materials' sums air, soft, bone, con, in type T: float, or float16 for a packet's lanes, M its
// comparisons' type (`on`: the lanes on their own ray). Each material's density is affine in
// HU, so where the corners are all one material their interpolated HU gives the blend of their
// densities. Across bone_min it does not: half a 3000 HU bar and half air interpolate to 1000 HU, whose bone density (offset +
// slope x HU) is 30 % above half the bar's, and rays along a thin plate's faces, every sample
// partly in it, read the plate up to 15 % too thick by a fraction that changes from ray to ray
// (a 1 mm plate on two 0.5 mm slices crossed 0.05 rad off its normal, where Joseph steps along
// the plate's 0.02 mm axis). So the corners are split at bone_min: the bone corners' weight and
// weighted HU, and the others', each part read as one material's (contrast within the first,
// air or soft tissue within the second), as Siddon reads the grid's piecewise-constant voxels.
#define BONE_W(T, g) select((T)(0.0f), (T)(1.0f), (g) >= bone_min)
#define BONE_H(T, g) select((T)(0.0f), (g), (g) >= bone_min)
// mix(a, b, t), a + (b - a) t, through FMA.
#define LERP(a, b, t) FMA((b) - (a), (t), (a))
#define BILINEAR(f, T, g00, g10, g01, g11) LERP(LERP(f(T, g00), f(T, g10), wb), LERP(f(T, g01), f(T, g11), wb), wc)
#define HU(T, g) (g)
#define SAMPLE(T, M, g00, g10, g01, g11, on, air, soft, bone, con) do { \
        const T h = BILINEAR(HU, T, g00, g10, g01, g11); \
        const T bone_w = BILINEAR(BONE_W, T, g00, g10, g01, g11), bone_h = BILINEAR(BONE_H, T, g00, g10, g01, g11); \
        const T rest_w = 1.0f - bone_w, rest_h = h - bone_h; \
        const T rho_w = select((T)(0.0f), fmax(rest_w + per_hu * rest_h, 0.0f), on); \
        const M is_air = rest_h <= air_max * rest_w, is_con = bone_h >= con_min * bone_w; \
        air += select((T)(0.0f), rho_w, is_air); \
        soft += select(rho_w, (T)(0.0f), is_air); \
        bone += select((T)(0.0f), bone_off * bone_w + bone_slope * bone_h, (on) && !is_con); \
        con += select((T)(0.0f), bone_w, (on) && is_con); } while (0)
// A packet's SAMPLE, where none of its sixteen samples has a bone corner (most of a chest's: soft
// tissue, lungs, air) without the bone parts, which are zero there: the same sums to the bit, a
// quarter less CPU time for a chest's cast (the bone path is taken in under a tenth of its steps),
// and 12-31 % less for two phases (BLEND, SPLIT: each phase's corners tested on their own).
// `bony`: whether a corner of any lane is at or above bone_min, lanes off their own ray included
// (they take the bone path, whose sums for them are masked the same). CORNERS answers it, from the
// voxels' int16s where it has them (ROWS, two compares of 32 shorts), else from the floats (BONY).
// A blend of two phases (BLEND) lies between the two, so either phase's answer covers it.
#define BONY(g00, g10, g01, g11) ANY16(fmax(fmax(g00, g10), fmax(g01, g11)) >= bone_min)
#define SAMPLE_PACKET(bony, g00, g10, g01, g11, on, air, soft, bone, con) do { \
        if (bony) { \
            SAMPLE(float16, int16, g00, g10, g01, g11, on, air, soft, bone, con); \
        } else { \
            const float16 h = BILINEAR(HU, float16, g00, g10, g01, g11); \
            const float16 rho_w = select((float16)(0.0f), fmax(1.0f + per_hu * h, 0.0f), on); \
            const int16 is_air = h <= air_max; \
            air += select((float16)(0.0f), rho_w, is_air); \
            soft += select(rho_w, (float16)(0.0f), is_air); \
        } } while (0)

// Joseph's method: one bilinear sample per slice along the ray's dominant axis, the corners
// split into materials at bone_min (see SAMPLE). out[p] = integral of each material's density
// along the ray (g/cm^3 * mm), as float4 (air, soft tissue, bone, contrast).
kernel void joseph_materials(global const short *vol,
#ifdef BLEND
                             global const short *vol_b, const float w_b,
#endif
                             const int nx, const int ny, const int nz, const int slab_axis,
                             global const float2 *dirs, global const uchar *mask,
                             constant float *geo, constant int *box, constant float *planes,
                             constant float *mat, global float4 *out)
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
    // The slices sampled lie within the outline too; the pixel's footprint below keeps the box's
    // [t0, t1], so the weights of the samples kept are the box-only cast's to the bit.
    float u0 = t0, u1 = t1;
    if (!clip_planes(planes, s, d, &u0, &u1)) { out[p] = acc; return; }

    const float3 ad = fabs(d);
    // Dominant axis a (a slab copy's own), in-slice axes b and c.
    const int a = slab_axis >= 0 ? slab_axis : ad.x >= ad.y && ad.x >= ad.z ? 0 : ad.y >= ad.z ? 1 : 2;
    const int b = a == 0 ? 1 : 0, c = a == 2 ? 1 : 2;
    const float sv[3] = {s.x, s.y, s.z};
    const float dv[3] = {d.x, d.y, d.z};
    const int dims[3] = {nx, ny, nz};
    int sa, sb, sc, oc;
    LAYOUT(slab_axis, dims, a, b, c, sa, sb, sc, oc);
    const int lo_i[3] = {box[0], box[1], box[2]};
    const int hi_i[3] = {box[4], box[5], box[6]};

    // Slices k with the plane index_a = k between u0 and u1, inside the content box.
    const float a0 = sv[a] + u0 * dv[a], a1 = sv[a] + u1 * dv[a];
    int k0 = (int)ceil(fmin(a0, a1)), k1 = (int)floor(fmax(a0, a1));
    k0 = max(k0, lo_i[a]);
    k1 = min(k1, hi_i[a]);
    // Per slice step in the in-slice axes, and mm of ray per slice.
    const float inv_da = 1.0f / dv[a];
    const float db = dv[b] * inv_da, dc = dv[c] * inv_da;
    const float b0 = sv[b] - sv[a] * db, c0 = sv[c] - sv[a] * dc;
    const float step_mm = fabs(inv_da) * mm_per_t;
    const float air_max = mat[0], bone_min = mat[1], con_min = mat[2];
    const float bone_off = mat[3], bone_slope = mat[4], per_hu = 0.001f;
    // In-slice coordinates stay inside the padding: clamp guards float rounding at the edges.
    const float bmax = (float)(dims[b] - 2), cmax = (float)(dims[c] - 2);
    // The pixel's footprint in voxels along b and c at the middle of the ray's path through the
    // volume: the steps to the neighbouring column's and row's rays there (t is depth in mm).
    float inv_b = 1.0f, inv_c = 1.0f;
    if (geo[12] > 0.0f) {
        const int rows = get_global_size(1) + get_global_offset(1);
        const float2 du = dirs[v * cols + (u > 0 ? u - 1 : min(u + 1, cols - 1))] - n;
        const float2 dw = dirs[(v > 0 ? v - 1 : min(v + 1, rows - 1)) * cols + u] - n;
        const float depth = geo[12] * 0.5f * (t0 + t1);
        inv_b = VOXEL_SLOPE(fmax(depth * (fabs(geo[3 * b] * du.x + geo[3 * b + 1] * du.y) +
                                          fabs(geo[3 * b] * dw.x + geo[3 * b + 1] * dw.y)), fabs(db)));
        inv_c = VOXEL_SLOPE(fmax(depth * (fabs(geo[3 * c] * du.x + geo[3 * c + 1] * du.y) +
                                          fabs(geo[3 * c] * dw.x + geo[3 * c + 1] * dw.y)), fabs(dc)));
    }
    const float off_b = 0.5f - 0.5f * inv_b, off_c = 0.5f - 0.5f * inv_c;
    const bool blocks_b = BLOCKS(inv_b > 1.0f), blocks_c = BLOCKS(inv_c > 1.0f);

    for (int k = k0; k <= k1; ++k) {
        const float fbv = clamp(b0 + (float)k * db, 0.0f, bmax);
        const float fcv = clamp(c0 + (float)k * dc, 0.0f, cmax);
        const int ib = (int)fbv, ic = (int)fcv;
        float wb = fbv - (float)ib, wc = fcv - (float)ic;
        if (blocks_b) wb = VOXEL_WEIGHT(wb, inv_b, off_b);
        if (blocks_c) wc = VOXEL_WEIGHT(wc, inv_c, off_c);
        const int base = k * sa + ib * sb + ic * sc;
        float g00 = vol[base], g10 = vol[base + sb], g01 = vol[base + oc], g11 = vol[base + sb + oc];
#ifdef BLEND
        g00 = mix(g00, (float)vol_b[base], w_b);
        g10 = mix(g10, (float)vol_b[base + sb], w_b);
        g01 = mix(g01, (float)vol_b[base + oc], w_b);
        g11 = mix(g11, (float)vol_b[base + sb + oc], w_b);
#endif
        SAMPLE(float, int, g00, g10, g01, g11, 1, acc.x, acc.y, acc.z, acc.w);
    }
    out[p] = acc * step_mm;
}

// The same integrals, sixteen neighbouring pixels of a detector row per work-item, in
// float16 vectors. CPU OpenCL drivers vectorise across work-items only for straight-line
// code, and every ray here runs its own loop, so the SIMD lanes are written out: on two
// CPU cores this is several times faster than joseph_materials (about 7x with AVX-512
// gathers, see UNALIGNED_PAIRS), with the same sums.
// The rays of a packet are nearly parallel; they share the dominant axis of the middle ray
// and step through the union of their slice ranges, each lane masked outside its own.
#define LANES 16
// The four corner voxels' indices of a packet's samples (ib, ic) in slice k: only where they are
// gathered, so that a packet read through row windows (ROWS) spends no multiply on them.
#define INDICES const int16 i00 = k * sa + ib * sb + ic * sc, i10 = i00 + sb, i01 = i00 + oc, i11 = i01 + sb
// clamp(x, 0, hi) as one max and one min instruction: PoCL's clamp(), and fmin() with a bound that
// is not a constant, add a compare and a blend per call to keep a NaN's rule (the cast 11-13 %
// slower), and x, a sample's position, is never NaN.
#define CLAMP16(x, hi) ({ const float16 m_ = fmax((x), 0.0f); select((float16)(hi), m_, m_ < (hi)); })
#define GATHER(v, i) ((float16)((v)[(i).s0], (v)[(i).s1], (v)[(i).s2], (v)[(i).s3], (v)[(i).s4], (v)[(i).s5], \
                                (v)[(i).s6], (v)[(i).s7], (v)[(i).s8], (v)[(i).s9], (v)[(i).sa], (v)[(i).sb], \
                                (v)[(i).sc], (v)[(i).sd], (v)[(i).se], (v)[(i).sf]))

// A packet's corners are HU times HU_SCALE (2^16): where a voxel is the high half of a 32-bit word
// (PAIR, ROWS), the word with its low half cleared is that, and the low one's is the word shifted
// up, one instruction each where sign-extending it takes two. Scaling by a power of two is exact, and
// the thresholds and per-HU slopes are scaled with it, so the sums are those of plain HU to the bit.
#define HU_SCALE 65536.0f
#define GATHER_HU(v, i) (GATHER(v, i) * HU_SCALE)
#define HI_HU(w) convert_float16((w) & (int)0xffff0000)
#define LO_HU(w) convert_float16((w) << 16)
#ifdef UNALIGNED_PAIRS
// Where the in-slice axis b is x (stride 1), a voxel and its b-neighbour are adjacent int16s:
// one 32-bit load fetches both, halving the loads. Such loads are only 2-byte aligned, which
// x86 and ARM CPUs accept; the renderer defines UNALIGNED_PAIRS only for CPU devices.
// (No access reaches the buffer's last voxel, so a 32-bit load never runs past its end:
// samples stay PAD slices inside along the dominant axis.)
#if defined(__AVX512F__) && !defined(NO_HW_GATHER)
// One hardware gather of sixteen 32-bit words instead of sixteen loads and inserts. PoCL
// runs kernels in the host's flat address space, so the global pointer is a plain one.
// (NO_HW_GATHER turns it off, so tests can check the portable path on such a CPU too.)
#define WORDS(v, i) __builtin_astype(__builtin_ia32_gathersiv16si(__builtin_astype((int16)(0), v16si), \
    (const void *)(ulong)(v), __builtin_astype((i), v16si), (ushort)0xffff, 2), int16)
#undef GATHER_HU
#define GATHER_HU(v, i) LO_HU(WORDS(v, i))
#else
#define W(v, i) (*(global const int *)((global const char *)(v) + 2 * (i)))
#define WORDS(v, i) ((int16)(W(v, (i).s0), W(v, (i).s1), W(v, (i).s2), W(v, (i).s3), W(v, (i).s4), W(v, (i).s5), \
                             W(v, (i).s6), W(v, (i).s7), W(v, (i).s8), W(v, (i).s9), W(v, (i).sa), W(v, (i).sb), \
                             W(v, (i).sc), W(v, (i).sd), W(v, (i).se), W(v, (i).sf)))
#endif
#define PAIR(v, i, lo, hi) do { const int16 w_ = WORDS(v, i); \
    lo = LO_HU(w_); hi = HI_HU(w_); } while (0)
#if defined(__AVX512BW__) && !defined(NO_HW_GATHER)
// Where a packet's sixteen samples lie, at every slice, in two neighbouring rows of the slice and
// within a few tens of voxels along them (`windows`, decided before the packet's loop), a row's
// 64 shorts (two vector loads) and a permute of shorts (AVX-512 BW) put each lane's voxel and its
// b-neighbour into its 32-bit word, as PAIR's gather does: the rows are those of lane `lane_c`,
// whose ray is the lowest across c at every slice, and the next two (a lane in the second row
// needs the third, c + 2); the shorts start at lane `lane_b`'s voxel, the lowest across b. The
// lanes' (ib, ic) are their voxels in slice k. A lane that rounds to the voxel below the lowest
// lane's (a near-tie) makes that slice gathered. A window reads rows of slice k, which has PAD
// slices after it in the buffer, so it never runs past the buffer's end.
#define WINDOWS_AVAILABLE
#define ROW_SHORTS 64
#define BROADCAST(x, lane) __builtin_astype(__builtin_ia32_permvarsi512(__builtin_astype((x), v16si), \
    __builtin_astype((int16)(lane), v16si)), int16)
typedef short v32hi __attribute__((vector_size(64)));
// Where the packet spans fewer voxels across b (`narrow`: under ROW_SHORTS_NARROW less the same
// margin at both ends, as at 512 pixels and more on the adult chest), half the window: one
// vector load and a permute of one register's shorts.
#define ROW_SHORTS_NARROW 32
#define SHORT_PAIRS_NARROW(v, at, idx) ({ global const int *w_ = (global const int *)((v) + (at)); \
    __builtin_astype(__builtin_ia32_permvarhi512(__builtin_astype(vload16(0, w_), v32hi), \
        __builtin_astype((idx), v32hi)), int16); })
#define WINDOW(v, at, idx) (narrow ? SHORT_PAIRS_NARROW(v, at, idx) : SHORT_PAIRS(v, at, idx))
#define SHORT_PAIRS(v, at, idx) ({ global const int *w_ = (global const int *)((v) + (at)); \
    __builtin_astype(__builtin_ia32_vpermi2varhi512(__builtin_astype(vload16(0, w_), v32hi), \
        __builtin_astype((idx), v32hi), __builtin_astype(vload16(1, w_), v32hi)), int16); })
#define BONY_WORDS(r0, r1) ((__builtin_ia32_cmpw512_mask(__builtin_astype((r0), v32hi), bone_s, 5, 0xffffffffu) | \
                             __builtin_ia32_cmpw512_mask(__builtin_astype((r1), v32hi), bone_s, 5, 0xffffffffu)) != 0)
#define ROWS(v, g00, g10, g01, g11, bony) do { \
    int16 r0_, r1_; \
    bool gather_ = !windows; \
    if (windows) { \
        const int16 bm_ = BROADCAST(ib, lane_b), cm_ = BROADCAST(ic, lane_c); \
        const int16 o_ = ib - bm_, first_ = (ic == cm_) & (o_ >= 0), idx_ = o_ | ((o_ + 1) << 16); \
        const int row_ = k * sa + cm_.s0 * sc + bm_.s0; \
        r0_ = WINDOW(v, row_, idx_); r1_ = WINDOW(v, row_ + sc, idx_); \
        if (!ALL16(first_)) { \
            if (ALL16(first_ | ((ic == cm_ + 1) & (o_ >= 0)))) { \
                const int16 r2_ = WINDOW(v, row_ + 2 * sc, idx_); \
                r0_ = select(r1_, r0_, first_); r1_ = select(r2_, r1_, first_); \
            } else gather_ = true; \
        } \
    } \
    if (gather_) { INDICES; r0_ = WORDS(v, i00); r1_ = WORDS(v, i01); } \
    bony = BONY_WORDS(r0_, r1_); \
    g00 = LO_HU(r0_); g10 = HI_HU(r0_); g01 = LO_HU(r1_); g11 = HI_HU(r1_); } while (0)
#else
#define ROWS(v, g00, g10, g01, g11, bony) do { INDICES; PAIR(v, i00, g00, g10); PAIR(v, i01, g01, g11); \
    bony = BONY(g00, g10, g01, g11); } while (0)
#endif
#define CORNERS(v, g00, g10, g01, g11, bony) do { \
    if (sb == 1) ROWS(v, g00, g10, g01, g11, bony); \
    else { INDICES; g00 = GATHER_HU(v, i00); g10 = GATHER_HU(v, i10); g01 = GATHER_HU(v, i01); g11 = GATHER_HU(v, i11); \
           bony = BONY(g00, g10, g01, g11); } } while (0)
#else
#define CORNERS(v, g00, g10, g01, g11, bony) do { INDICES; \
    g00 = GATHER_HU(v, i00); g10 = GATHER_HU(v, i10); g01 = GATHER_HU(v, i01); g11 = GATHER_HU(v, i11); \
    bony = BONY(g00, g10, g01, g11); } while (0)
#endif

// A packet's four sums times each lane's mm per step (0 off the beam) as its sixteen pixels'
// float4s: a whole packet in four vector stores of the interleaved lanes, the one at a row's end
// lane by lane.
#define QUAD(A, S, B, C, i, j, k, l) (float16)(A.s##i, S.s##i, B.s##i, C.s##i, A.s##j, S.s##j, B.s##j, C.s##j, \
                                              A.s##k, S.s##k, B.s##k, C.s##k, A.s##l, S.s##l, B.s##l, C.s##l)
#define STORE_LINES(o, air, soft, bone, con) do { \
    const float16 A_ = select((float16)(0.0f), air * step_mm, hit), S_ = select((float16)(0.0f), soft * step_mm, hit); \
    const float16 B_ = select((float16)(0.0f), bone * step_mm, hit), C_ = select((float16)(0.0f), con * step_mm, hit); \
    if (whole) { \
        global float *f_ = (global float *)((o) + p0); \
        vstore16(QUAD(A_, S_, B_, C_, 0, 1, 2, 3), 0, f_); vstore16(QUAD(A_, S_, B_, C_, 4, 5, 6, 7), 1, f_); \
        vstore16(QUAD(A_, S_, B_, C_, 8, 9, a, b), 2, f_); vstore16(QUAD(A_, S_, B_, C_, c, d, e, f), 3, f_); \
    } else { \
        for (int l = 0; l < LANES; ++l) \
            if (u0 + l < cols) (o)[p0 + l] = (float4)(A_[l], S_[l], B_[l], C_[l]); \
    } } while (0)

// The second phase's arguments of the packet kernels (BLEND: mixed in the cast; SPLIT: cast into
// its own integrals, out_b), in the kernel's order; SLABBED picks each packet's grid from two.
#if defined(BLEND)
#define SECOND_PARAMS global const short *vol_b, const float w_b,
#define SECOND_ARGS(vb) vb, w_b,
#elif defined(SPLIT)
#define SECOND_PARAMS global const short *vol_b,
#define SECOND_ARGS(vb) vb,
#else
#define SECOND_PARAMS
#define SECOND_ARGS(vb)
#endif
#ifdef SPLIT
#define OUT_B_PARAM , global float4 *out_b
#define OUT_B_ARG , out_b
#else
#define OUT_B_PARAM
#define OUT_B_ARG
#endif

// One packet's sixteen rays (directions nxv, nyv; on the beam where on_beam) through one voxel grid.
//
// SPLIT: two phases on one voxel grid in one pass, each phase's integrals to its own output
// (out, out_b): the projection cache blends them later in projection space, and sampling both
// at the same positions costs little more than one, since the addresses are shared.
inline void packet_lines(global const short *vol, SECOND_PARAMS
                         const int nx, const int ny, const int nz, const int slab_axis,
                         global const float2 *dirs, constant float *geo, constant int *box, constant float *planes,
                         constant float *mat, const int cols, global float4 *out OUT_B_PARAM,
                         const int u0, const int v, const float16 nxv, const float16 nyv, const int16 on_beam)
{
    const int p0 = v * cols + u0;
    const bool whole = u0 + LANES <= cols;
    const float16 dx = geo[0] * nxv + geo[1] * nyv + geo[2];
    const float16 dy = geo[3] * nxv + geo[4] * nyv + geo[5];
    const float16 dz = geo[6] * nxv + geo[7] * nyv + geo[8];
    const float s[3] = {geo[9], geo[10], geo[11]};
    const float16 mm_per_t = sqrt(nxv * nxv + nyv * nyv + 1.0f);
    const float3 dm = fabs((float3)(dx[LANES / 2], dy[LANES / 2], dz[LANES / 2]));
    const int a = slab_axis >= 0 ? slab_axis : dm.x >= dm.y && dm.x >= dm.z ? 0 : dm.y >= dm.z ? 1 : 2;
    const int b = a == 0 ? 1 : 0, c = a == 2 ? 1 : 2;
    const float16 dv[3] = {dx, dy, dz};
    const int lo_i[3] = {box[0], box[1], box[2]};
    const int hi_i[3] = {box[4], box[5], box[6]};
    const int dims[3] = {nx, ny, nz};
    int sa, sb, sc, oc;
    LAYOUT(slab_axis, dims, a, b, c, sa, sb, sc, oc);

    // Clip every lane to the content box grown by one voxel (slab method, as clip_box).
    float16 t0 = 0.0f, t1 = INFINITY;
    int16 hit = on_beam;
    for (int ax = 0; ax < 3; ++ax) {
        const float lo = (float)lo_i[ax] - 1.0f, hi = (float)hi_i[ax] + 1.0f;
        const float16 inv = 1.0f / dv[ax];
        const float16 ta = (lo - s[ax]) * inv, tb = (hi - s[ax]) * inv;
        const int16 par = dv[ax] == 0.0f;
        if (s[ax] < lo || s[ax] > hi) hit &= ~par;
        t0 = select(fmax(t0, fmin(ta, tb)), t0, par);
        t1 = select(fmin(t1, fmax(ta, tb)), t1, par);
    }
    hit &= t1 > t0;
    // And to the outline's planes (as clip_planes), into [e0, e1]: the footprint below keeps
    // the box's [t0, t1], as joseph_materials does.
    float16 e0 = t0, e1 = t1;
    const int n_planes = (int)planes[0];
    for (int j = 0; j < n_planes; ++j) {
        constant float *q = planes + 1 + 5 * j;
        const float ns = q[0] * s[0] + q[1] * s[1] + q[2] * s[2];
        const float16 nd = q[0] * dx + q[1] * dy + q[2] * dz;
        const float16 inv = 1.0f / nd;
        const float16 ta = (q[3] - ns) * inv, tb = (q[4] - ns) * inv;
        const int16 par = nd == 0.0f;
        if (ns < q[3] || ns > q[4]) hit &= ~par;
        e0 = select(fmax(e0, fmin(ta, tb)), e0, par);
        e1 = select(fmin(e1, fmax(ta, tb)), e1, par);
    }
    hit &= e1 > e0;
    const float16 a0 = s[a] + e0 * dv[a], a1 = s[a] + e1 * dv[a];
    int16 k0 = max(convert_int16_rtp(fmin(a0, a1)), lo_i[a]);
    int16 k1 = min(convert_int16_rtn(fmax(a0, a1)), hi_i[a]);
    k0 = select((int16)(INT_MAX), k0, hit);
    k1 = select((int16)(INT_MIN), k1, hit);
    int kmin = INT_MAX, kmax = INT_MIN, kin = INT_MIN, kout = INT_MAX;
    for (int l = 0; l < LANES; ++l) {
        kmin = min(kmin, k0[l]);
        kmax = max(kmax, k1[l]);
        kin = max(kin, k0[l]);
        kout = min(kout, k1[l]);
    }
    const float16 inv_da = 1.0f / dv[a];
    const float16 db = dv[b] * inv_da, dc = dv[c] * inv_da;
    const float16 b0 = s[b] - s[a] * db, c0 = s[c] - s[a] * dc;
    const float16 step_mm = fabs(inv_da) * mm_per_t;
    // The packet's corners are HU x HU_SCALE, and so are its thresholds (see HU_SCALE).
    const float air_max = mat[0] * HU_SCALE, bone_min = mat[1] * HU_SCALE, con_min = mat[2] * HU_SCALE;
    const float bone_off = mat[3], bone_slope = mat[4] / HU_SCALE, per_hu = 0.001f / HU_SCALE;
    const float bmax = (float)(dims[b] - 2), cmax = (float)(dims[c] - 2);
#ifdef WINDOWS_AVAILABLE
    const short bone_ms = (short)clamp(ceil(mat[1]), -32768.0f, 32767.0f);
    const v32hi bone_s = __builtin_astype((int16)(((int)bone_ms << 16) | (int)(ushort)bone_ms), v32hi);
    // All rays pass through the focal spot, outside the volume, so along the ray the lanes keep
    // their order across b and across c, and their spread across either is largest at the first
    // or the last slice (a difference of two lines): the spreads and the lowest lanes there
    // decide `windows` for all the slices between (with a few voxels' margin below ROWS' limits).
    bool windows = false, narrow = false;
    int lane_b = 0, lane_c = 0;
    if (sb == 1 && kmin <= kmax) {
        const float span_b = ROW_SHORTS - 4;
        const float16 fb0 = b0 + (float)kmin * db, fb1 = b0 + (float)kmax * db;
        const float16 fc0 = c0 + (float)kmin * dc, fc1 = c0 + (float)kmax * dc;
        int last_b = 0, last_c = 0;
        float hb0 = fb0[0], hb1 = fb1[0], hc0 = fc0[0], hc1 = fc1[0];       // the highest
        for (int l = 1; l < LANES; ++l) {
            if (fb0[l] < fb0[lane_b]) lane_b = l;
            if (fb1[l] < fb1[last_b]) last_b = l;
            if (fc0[l] < fc0[lane_c]) lane_c = l;
            if (fc1[l] < fc1[last_c]) last_c = l;
            hb0 = fmax(hb0, fb0[l]); hb1 = fmax(hb1, fb1[l]); hc0 = fmax(hc0, fc0[l]); hc1 = fmax(hc1, fc1[l]);
        }
        narrow = hb0 - fb0[lane_b] < ROW_SHORTS_NARROW - 4 && hb1 - fb1[lane_b] < ROW_SHORTS_NARROW - 4;
        windows = lane_b == last_b && lane_c == last_c && hb0 - fb0[lane_b] < span_b && hb1 - fb1[lane_b] < span_b &&
                  hc0 - fc0[lane_c] < 0.99f && hc1 - fc1[lane_c] < 0.99f;
    }
#endif
    // Each lane's pixel footprint along b and c, as joseph_materials takes it (see VOXEL_WEIGHT).
    float16 inv_b = 1.0f, inv_c = 1.0f;
    if (geo[12] > 0.0f) {
        const int rows = get_global_size(1) + get_global_offset(1);
        const int vn = v > 0 ? v - 1 : min(v + 1, rows - 1);
        float16 dux, duy, dwx, dwy;
        for (int l = 0; l < LANES; ++l) {
            const int u = min(u0 + l, cols - 1), un = u > 0 ? u - 1 : min(u + 1, cols - 1);
            const float2 du = dirs[v * cols + un] - (float2)(nxv[l], nyv[l]);
            const float2 dw = dirs[vn * cols + u] - (float2)(nxv[l], nyv[l]);
            dux[l] = du.x; duy[l] = du.y; dwx[l] = dw.x; dwy[l] = dw.y;
        }
        const float16 depth = geo[12] * 0.5f * (t0 + t1);
        const float ab0 = geo[3 * b], ab1 = geo[3 * b + 1], ac0 = geo[3 * c], ac1 = geo[3 * c + 1];
        inv_b = VOXEL_SLOPE(fmax(depth * (fabs(ab0 * dux + ab1 * duy) + fabs(ab0 * dwx + ab1 * dwy)), fabs(db)));
        inv_c = VOXEL_SLOPE(fmax(depth * (fabs(ac0 * dux + ac1 * duy) + fabs(ac0 * dwx + ac1 * dwy)), fabs(dc)));
    }
    const float16 off_b = 0.5f - 0.5f * inv_b, off_c = 0.5f - 0.5f * inv_c;
    // A packet none of whose rays meets a voxel larger than its footprint keeps linear weights
    // without a cycle spent on them.
    const bool blocks_b = BLOCKS(ANY16(inv_b > 1.0f)), blocks_c = BLOCKS(ANY16(inv_c > 1.0f));
    float16 acc_air = 0.0f, acc_soft = 0.0f, acc_bone = 0.0f, acc_con = 0.0f;
#ifdef SPLIT
    float16 bcc_air = 0.0f, bcc_soft = 0.0f, bcc_bone = 0.0f, bcc_con = 0.0f;
#endif
    // One Joseph step at slice k. Between kin and kout every lane is on its own ray, inside the
    // content box grown by a voxel, so its in-slice position is inside the padding without the
    // clamp (MIDDLE: neither the clamp nor the lanes' mask spent); at the packet's ends, EDGE.
#define STEP(k, fb_, fc_, on) do { \
        const float16 fb = fb_, fc = fc_; \
        const int16 ib = convert_int16(fb), ic = convert_int16(fc); \
        float16 wb = fb - convert_float16(ib), wc = fc - convert_float16(ic); \
        if (blocks_b) wb = VOXEL_WEIGHT(wb, inv_b, off_b); \
        if (blocks_c) wc = VOXEL_WEIGHT(wc, inv_c, off_c); \
        float16 g00, g10, g01, g11; \
        bool bony, bony_b; \
        CORNERS(vol, g00, g10, g01, g11, bony); \
        SECOND_PHASE(on); \
        SAMPLE_PACKET(bony, g00, g10, g01, g11, on, acc_air, acc_soft, acc_bone, acc_con); } while (0)
#if defined(BLEND)
#define SECOND_PHASE(on) float16 b00, b10, b01, b11; CORNERS(vol_b, b00, b10, b01, b11, bony_b); \
        g00 = mix(g00, b00, w_b); g10 = mix(g10, b10, w_b); g01 = mix(g01, b01, w_b); g11 = mix(g11, b11, w_b); \
        bony |= bony_b
#elif defined(SPLIT)
#define SECOND_PHASE(on) float16 b00, b10, b01, b11; CORNERS(vol_b, b00, b10, b01, b11, bony_b); \
        SAMPLE_PACKET(bony_b, b00, b10, b01, b11, on, bcc_air, bcc_soft, bcc_bone, bcc_con)
#else
#define SECOND_PHASE(on) (void)bony_b
#endif
#define EDGE(k) STEP(k, CLAMP16(b0 + (float)(k) * db, bmax), CLAMP16(c0 + (float)(k) * dc, cmax), (k >= k0) & (k <= k1))
#define MIDDLE(k) STEP(k, b0 + (float)(k) * db, c0 + (float)(k) * dc, (int16)(-1))
    const int mid0 = kin <= kout ? kin : kmax + 1, mid1 = kin <= kout ? kout : kmax;
    for (int k = kmin; k < mid0; ++k) EDGE(k);
    for (int k = mid0; k <= mid1; ++k) MIDDLE(k);
    for (int k = mid1 + 1; k <= kmax; ++k) EDGE(k);
    STORE_LINES(out, acc_air, acc_soft, acc_bone, acc_con);
#ifdef SPLIT
    STORE_LINES(out_b, bcc_air, bcc_soft, bcc_bone, bcc_con);
#endif
}

// SLABBED: a moving frame through pre-integrated slabs where its rays allow (slabs.py): each
// packet none of whose rays on the beam shifts more than the rule's pixels within a slab reads
// the slab copy (vol_s, its own grid: shape, layout, geometry, box and outline); the others read
// the full volume, as the plain build would. rule (constant float[4]): the slab's axis a, then
// r_b, r_c: a ray's shift within a slab in pixels is |(r_b d_b, r_c d_c)| / |d_a| for its
// direction d in the full volume's indices, then the most pixels allowed.
#ifdef SLABBED
#if defined(BLEND) || defined(SPLIT)
#define SLAB_SECOND_PARAM global const short *vol_sb,
#else
#define SLAB_SECOND_PARAM
#endif
#define SLABBED_PARAMS , global const short *vol_s, SLAB_SECOND_PARAM const int snx, const int sny, const int snz, \
    const int s_axis, constant float *geo_s, constant int *box_s, constant float *planes_s, constant float *rule
#else
#define SLABBED_PARAMS
#endif
kernel void joseph_packet(global const short *vol, SECOND_PARAMS
                          const int nx, const int ny, const int nz, const int slab_axis,
                          global const float2 *dirs, global const uchar *mask,
                          constant float *geo, constant int *box, constant float *planes,
                          constant float *mat, const int cols, global float4 *out OUT_B_PARAM SLABBED_PARAMS)
{
    const int u0 = get_global_id(0) * LANES, v = get_global_id(1);
    const int p0 = v * cols + u0;
    float16 nxv, nyv;
    int16 on_beam;
    // A whole packet's directions and beam mask are vector loads (two and one), split into lanes by
    // swizzles; the packet at a row's end, lane by lane.
    if (u0 + LANES <= cols) {
        global const float *df = (global const float *)(dirs + p0);
        const float16 d0 = vload16(0, df), d1 = vload16(1, df);
        nxv = (float16)(d0.even, d1.even);
        nyv = (float16)(d0.odd, d1.odd);
        on_beam = convert_int16(vload16(0, mask + p0)) != 0;
    } else {
        for (int l = 0; l < LANES; ++l) {
            const int u = min(u0 + l, cols - 1);
            const float2 n = dirs[v * cols + u];
            nxv[l] = n.x;
            nyv[l] = n.y;
            on_beam[l] = (u0 + l < cols) && mask[v * cols + u] ? -1 : 0;
        }
    }
#ifdef SLABBED
    const int ra = (int)rule[0], rb = ra == 0 ? 1 : 0, rc = ra == 2 ? 1 : 2;
    const float16 da = geo[3 * ra] * nxv + geo[3 * ra + 1] * nyv + geo[3 * ra + 2];
    const float16 sb_ = rule[1] * (geo[3 * rb] * nxv + geo[3 * rb + 1] * nyv + geo[3 * rb + 2]);
    const float16 sc_ = rule[2] * (geo[3 * rc] * nxv + geo[3 * rc + 1] * nyv + geo[3 * rc + 2]);
    const bool thin = !ANY16((sb_ * sb_ + sc_ * sc_ > (rule[3] * rule[3]) * (da * da)) & on_beam);
    packet_lines(thin ? vol_s : vol, SECOND_ARGS(thin ? vol_sb : vol_b) thin ? snx : nx, thin ? sny : ny,
                 thin ? snz : nz, thin ? s_axis : slab_axis, dirs, thin ? geo_s : geo, thin ? box_s : box,
                 thin ? planes_s : planes, mat, cols, out OUT_B_ARG, u0, v, nxv, nyv, on_beam);
#else
    packet_lines(vol, SECOND_ARGS(vol_b) nx, ny, nz, slab_axis, dirs, geo, box, planes, mat, cols, out OUT_B_ARG,
                 u0, v, nxv, nyv, on_beam);
#endif
}

// Energy-integrating detector: I/I0 = sum_e w_e exp(-sum_m mu_rho[e][m] * L_m), with L in
// g/cm^3 * mm (hence the 0.1 to g/cm^2) and w_e = N0(E) E normalised to sum 1. Pixels
// outside the mask read 0 (no signal).
// `lines_b` with weight w_b > 0 blends two phases' integrals first (see polychromatic_packet).
kernel void polychromatic(global const float4 *lines, global const float4 *lines_b, const float w_b,
                          global const uchar *mask,
                          constant float *weights, constant float4 *mu_rho, const int n_e,
                          global float *out)
{
    const int p = get_global_id(0);
    if (!mask[p]) { out[p] = 0.0f; return; }
    const float4 L = (w_b > 0.0f ? mix(lines[p], lines_b[p], w_b) : lines[p]) * 0.1f;
    float sum = 0.0f;
    for (int e = 0; e < n_e; ++e)
        sum += weights[e] * exp(-dot(mu_rho[e], L));
    out[p] = sum;
}

// The same sum for sixteen pixels per work-item, so a CPU evaluates exp() in SIMD.
// `lines_b` with weight w_b > 0: the pixel's integrals are (1 - w_b) lines + w_b lines_b, the
// projection cache's blend of two phases (exact: a line integral is linear in the density),
// without a pass of its own.
kernel void polychromatic_packet(global const float4 *lines, global const float4 *lines_b, const float w_b,
                                 global const uchar *mask,
                                 constant float *weights, constant float4 *mu_rho, const int n_e,
                                 const int n_pixels, global float *out)
{
    const int p0 = get_global_id(0) * LANES;
    const bool whole = p0 + LANES <= n_pixels;
    int16 on;
    if (whole) {
        on = convert_int16(vload16(0, mask + p0)) != 0;
    } else {
        for (int l = 0; l < LANES; ++l)
            on[l] = p0 + l < n_pixels && mask[p0 + l] ? -1 : 0;
    }
    float16 sum = 0.0f;
    if (ANY16(on)) {    // a packet wholly outside the beam reads nothing
        float16 La, Ls, Lb, Lc;
        if (whole) {
            // Sixteen pixels' float4s as four float16s, split into one vector per material.
            global const float *fa = (global const float *)(lines + p0);
            float16 v0 = vload16(0, fa), v1 = vload16(1, fa), v2 = vload16(2, fa), v3 = vload16(3, fa);
            if (w_b > 0.0f) {
                global const float *fb = (global const float *)(lines_b + p0);
                v0 = mix(v0, vload16(0, fb), w_b); v1 = mix(v1, vload16(1, fb), w_b);
                v2 = mix(v2, vload16(2, fb), w_b); v3 = mix(v3, vload16(3, fb), w_b);
            }
            La = 0.1f * (float16)(v0.s048c, v1.s048c, v2.s048c, v3.s048c);
            Ls = 0.1f * (float16)(v0.s159d, v1.s159d, v2.s159d, v3.s159d);
            Lb = 0.1f * (float16)(v0.s26ae, v1.s26ae, v2.s26ae, v3.s26ae);
            Lc = 0.1f * (float16)(v0.s37bf, v1.s37bf, v2.s37bf, v3.s37bf);
        } else {
            for (int l = 0; l < LANES; ++l) {
                const int q = min(p0 + l, n_pixels - 1);
                float4 L = lines[q];
                if (w_b > 0.0f) L = mix(L, lines_b[q], w_b);
                L *= 0.1f;
                La[l] = L.x; Ls[l] = L.y; Lb[l] = L.z; Lc[l] = L.w;
            }
        }
        for (int e = 0; e < n_e; ++e) {
            const float4 m = mu_rho[e];
            sum += weights[e] * exp(-(m.x * La + m.y * Ls + m.z * Lb + m.w * Lc));
        }
        sum = select((float16)(0.0f), sum, on);
    }
    if (whole) {
        vstore16(sum, 0, out + p0);
    } else {
        for (int l = 0; l < LANES; ++l)
            if (p0 + l < n_pixels) out[p0 + l] = sum[l];
    }
}

// Quantum noise: each pixel's relative intensity becomes a photon count drawn around
// lam = intensity * n0 (photons expected per pixel with nothing in the beam), returned
// relative to n0 again. Poisson by inversion of its distribution function (one uniform, the
// terms lam^k e^-lam / k! summed until they pass it) below GAUSSIAN_ABOVE photons, its normal
// approximation (Box-Muller) above, where the two agree to well under the noise.
// The uniforms come from a counter-based hash of (seed, pixel, draw), so a frame's noise is
// the same on every device and for every work-group split, and needs no stored state.
#define GAUSSIAN_ABOVE 30.0f
//: The inversion stops where the terms left are below this (their sum is then ~1e-7 of the
//: distribution): float sums never quite reach 1, and a uniform above them must not run on.
#define POISSON_TAIL 1e-7f
inline uint hash32(uint x)     // "lowbias32" (C. Wellons): a bijection with good avalanche
{
    x ^= x >> 16; x *= 0x7feb352dU; x ^= x >> 15; x *= 0x846ca68bU; x ^= x >> 16;
    return x;
}
inline float uniform_open(uint key, uint draw)     // in (0, 1], 24 bits
{
    return (float)((hash32(key + draw * 0x9e3779b9U) >> 8) + 1u) * (1.0f / 16777216.0f);
}
kernel void quantum_noise(global float *img, const float n0, const uint seed)
{
    const int p = get_global_id(0);
    const float lam = fmax(img[p], 0.0f) * n0;
    const uint key = hash32(hash32((uint)p) ^ seed);
    float count;
    const float u0 = uniform_open(key, 0u);
    if (lam >= GAUSSIAN_ABOVE) {
        const float r = sqrt(-2.0f * log(u0));
        count = fmax(lam + sqrt(lam) * r * cos(6.2831853f * uniform_open(key, 1u)), 0.0f);
    } else {
        float term = exp(-lam), sum = term;
        uint k = 0u;
        while (u0 > sum && (term > POISSON_TAIL || (float)k < lam)) {
            ++k;
            term *= lam / (float)k;
            sum += term;
        }
        count = (float)k;
    }
    img[p] = count / n0;
}

// The same noise for sixteen pixels per work-item, the same draws for the same (seed, pixel),
// all in SIMD: the normal approximation for every lane, and the inversion over the whole
// packet, masked, only where a lane is below GAUSSIAN_ABOVE (the densest rays). A CPU driver
// cannot vectorise quantum_noise's per-pixel branch and loop, so this costs a fraction of it.
inline uint16 hash32_16(uint16 x)
{
    x ^= x >> 16; x *= 0x7feb352dU; x ^= x >> 15; x *= 0x846ca68bU; x ^= x >> 16;
    return x;
}
inline float16 uniform_open16(uint16 key, uint16 draw)
{
    return convert_float16((hash32_16(key + draw * 0x9e3779b9U) >> 8) + 1u) * (1.0f / 16777216.0f);
}
kernel void quantum_noise_packet(global float *img, const float n0, const uint seed, const int n_pixels)
{
    const int p0 = get_global_id(0) * LANES;
    const bool whole = p0 + LANES <= n_pixels;
    float16 lam;
    if (whole) {
        lam = vload16(0, img + p0);
    } else {
        for (int l = 0; l < LANES; ++l)
            lam[l] = img[min(p0 + l, n_pixels - 1)];
    }
    lam = fmax(lam, 0.0f) * n0;
    const uint16 pix = (uint16)((uint)p0) + (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const uint16 key = hash32_16(hash32_16(pix) ^ seed);
    const float16 u0 = uniform_open16(key, (uint16)(0u));
    const float16 r = sqrt(-2.0f * log(u0));
    float16 count = fmax(lam + sqrt(lam) * r * cos(6.2831853f * uniform_open16(key, (uint16)(1u))), 0.0f);
    const int16 low = lam < GAUSSIAN_ABOVE;
    if (ANY16(low)) {
        // The inversion over the packet, masked: lanes above the threshold stop at once.
        float16 term = exp(-lam), sum = term;
        float16 k = 0.0f;
        int16 going = low & (u0 > sum);
        while (ANY16(going)) {
            k = select(k, k + 1.0f, going);
            term = select(term, term * lam / k, going);
            sum = select(sum, sum + term, going);
            going &= (u0 > sum) & ((term > POISSON_TAIL) | (k < lam));
        }
        count = select(count, k, low);
    }
    count /= n0;
    if (whole) {
        vstore16(count, 0, img + p0);
    } else {
        for (int l = 0; l < LANES; ++l)
            if (p0 + l < n_pixels) img[p0 + l] = count[l];
    }
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
    // The box alone clips, not the outline (clip_planes): this path is the exact one, held to the
    // closed form and to the NumPy Siddon of every voxel, and the voxels at or below EMPTY_MAX_HU
    // the outline drops are not all -1000: a surface's partial-volume voxels (-1000 to -900 HU,
    // up to 0.1 g/cm^3) lie all along a curved body's edge, the box's faces touch few of them.
    // Clipped to the outline, the partial-volume ellipsoid's rays (bench drr's accuracy table)
    // moved 0.25 % from the NumPy reference at worst, over that bar's 0.1 %.

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

// Projection-space blend of two phases' cached material integrals (appliance/xray/
// projection_cache.py): out = (1 - w) * a + w * b, exact for the linear blend of the two
// phases' material densities, since a line integral is linear in the density.
kernel void blend_lines(global const float4 *a, global const float4 *b, const float w, global float4 *out)
{
    const int p = get_global_id(0);
    out[p] = mix(a[p], b[p], w);
}

// The exposure control's sample of a frame's material integrals: the pixels `index` names
// (a thousand of the measuring field's), so the host reads kilobytes, not the whole frame.
kernel void gather_lines(global const float4 *lines, global const int *index, global float4 *out)
{
    const int i = get_global_id(0);
    out[i] = lines[index[i]];
}

// Pre-integrated slabs (slabs.py): `thick` slices along `axis` averaged into one slab, 2 or 1.
// Two: a cast through the slab grid steps two voxels at a time yet every voxel counts (HU,
// hence density, is averaged: the line integral through a pair is kept). One: the phase itself,
// only laid out for rays along the axis (a lateral view's full-volume cast then reads rows as a
// posterior-anterior one does). Slab q >= PAD along the axis holds the padded input slices from
// thick * (q - PAD) + PAD on, the last slab maybe a slice and the padding's air. Rounded half to
// even in integers (rint on floats was a library call per voxel, ten times the copy itself): the
// int16 average is unbiased.
#define SLAB_TILE 16
// The mean of `thick` (2 or 4) slices' HU from their sum s, x.5 (2) or x.5 of 4 to the even
// neighbour; floor(s / thick) by the shift holds for negative sums too.
inline int mean_even_n(int s, int thick)
{
    const int sh = thick == 4 ? 2 : 1, mid = thick >> 1, q = s >> sh, r = s & (thick - 1);
    return q + ((r > mid) | ((r == mid) & (q & 1)));
}
#define MEAN_EVEN16(s, thick) ({ const int16 s_ = (s), q_ = s_ >> ((thick) == 4 ? 2 : 1), r_ = s_ & ((thick) - 1); \
    const int h_ = (thick) >> 1; q_ + (select((int16)(0), (int16)(1), r_ > h_) | (select((int16)(0), (int16)(1), r_ == h_) & q_ & 1)); })

// Sixteen consecutive slabs of `thick` (1, 2 or 4) voxels each from `src` on, along x.
inline short16 slab_tile_row(global const short *src, int thick)
{
    if (thick == 1)
        return vload16(0, src);
    const int16 a0 = convert_int16(vload16(0, src)), a1 = convert_int16(vload16(1, src));
    int16 sum = (int16)(a0.even, a1.even) + (int16)(a0.odd, a1.odd);     // pairs
    if (thick == 4) {
        const int16 a2 = convert_int16(vload16(2, src)), a3 = convert_int16(vload16(3, src));
        const int16 later = (int16)(a2.even, a3.even) + (int16)(a2.odd, a3.odd);
        sum = (int16)(sum.even, later.even) + (int16)(sum.odd, later.odd);  // pairs of pairs
    }
    return convert_short16(MEAN_EVEN16(sum, thick));       // sixteen at a time
}

// The slab grid (padded shape ox, oy, oz) of the volume `vol` (plain layout, nx x ny x ...,
// `n_in` slices along `axis`) along `axis`, slabs of `thick` slices (1, 2 or 4; a last slab past
// the volume's end takes air for the missing slices), laid out for rays along it (see LAYOUT):
// rows along b, then slabs along a, then c. One work-item per c, looping over its slabs and
// rows: PoCL gives each tiny work-item a work-group of its own.
kernel void slab_rows(global const short *vol, const int nx, const int ny, const int axis, const int thick,
                      const int n_in, const int ox, const int oy, const int oz, global short *out)
{
    const int ic = get_global_id(0);
    const int dims[3] = {ox, oy, oz};
    const size_t stride[3] = {1, (size_t)nx, (size_t)nx * ny};
    const int b = axis == 0 ? 1 : 0, c = axis == 2 ? 1 : 2;
    const int na = dims[axis], nb = dims[b];
    const size_t sa = stride[axis], sb = stride[b], sc = stride[c];
    for (int k = 0; k < na; ++k) {
        global short *row = out + ((size_t)ic * na + k) * nb;
        if (k < PAD || k >= na - PAD) {
            for (int i = 0; i < nb; ++i) row[i] = -1000;
            continue;
        }
        const int first = thick * (k - PAD) + PAD;              // the slab's first slice of the input
        global const short *s0 = vol + (size_t)first * sa + ic * sc;
        if (axis == 0 && k + SLAB_TILE <= na - PAD && first + thick * SLAB_TILE <= n_in) {
            // Along x the output's rows are the input's columns: SLAB_TILE of them at once, each
            // input row read as vectors (one, two or four), so the reads run along memory, not across it.
            int ib = 0;
            for (; ib + SLAB_TILE <= nb; ib += SLAB_TILE) {
                // A tile of sixteen input rows by sixteen slabs, written out as sixteen output rows.
                short16 t[SLAB_TILE];
                for (int m = 0; m < SLAB_TILE; ++m)
                    t[m] = slab_tile_row(s0 + (ib + m) * sb, thick);
                for (int l = 0; l < SLAB_TILE; ++l)
                    vstore16((short16)(t[0][l], t[1][l], t[2][l], t[3][l], t[4][l], t[5][l], t[6][l], t[7][l],
                                       t[8][l], t[9][l], t[10][l], t[11][l], t[12][l], t[13][l], t[14][l], t[15][l]),
                             0, row + (size_t)l * nb + ib);
            }
            for (; ib < nb; ++ib) {
                const short16 v = slab_tile_row(s0 + ib * sb, thick);
                for (int l = 0; l < SLAB_TILE; ++l) row[(size_t)l * nb + ib] = v[l];
            }
            k += SLAB_TILE - 1;
            continue;
        }
        if (thick == 1) {
            for (int ib = 0; ib < nb; ++ib) row[ib] = s0[ib * sb];
            continue;
        }
        int ib = 0;
        if (sb == 1 && first + thick <= n_in) {
            // Across x (rays along y or z) the output's rows are the input's: sixteen at a time.
            for (; ib + 16 <= nb; ib += 16) {
                int16 sum = convert_int16(vload16(0, s0 + ib));
                for (int j = 1; j < thick; ++j)
                    sum += convert_int16(vload16(0, s0 + j * sa + ib));
                vstore16(convert_short16(MEAN_EVEN16(sum, thick)), 0, row + ib);
            }
        }
        for (; ib < nb; ++ib) {
            int sum = 0;
            for (int j = 0; j < thick; ++j)
                sum += first + j < n_in ? s0[j * sa + ib * sb] : -1000;
            row[ib] = (short)mean_even_n(sum, thick);
        }
    }
}
