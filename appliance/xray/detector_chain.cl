// The detector after the cast, on the device, for a GPU: a display frame's image stays in device
// memory from the cast to the monitor's grey scale (device_chain.py strings these together and
// owns the tables). One work-item a pixel; a GPU's driver needs nothing wider.

// Resampling along rows by a tap table: dst[r, j] = sum_k w[j, k] src[r, idx[j, k]]. The
// Gaussian blurs (OpenCV's taps, its reflect-101 border folded into idx), the glare's coarse
// grid (INTER_AREA's weights) and its way back (INTER_LINEAR's) are all such tables.
kernel void resample_rows(global const float *src, global float *dst, global const int *idx,
                          global const float *w, const int taps, const int src_cols, const int dst_cols)
{
    const int j = get_global_id(0), r = get_global_id(1);
    const global float *row = src + (size_t)r * src_cols;
    const global int *ix = idx + (size_t)j * taps;
    const global float *wx = w + (size_t)j * taps;
    float s = 0.0f;
    for (int k = 0; k < taps; ++k)
        s += wx[k] * row[ix[k]];
    dst[(size_t)r * dst_cols + j] = s;
}

// The same down the columns: dst[i, c] = sum_k w[i, k] src[idx[i, k], c].
kernel void resample_cols(global const float *src, global float *dst, global const int *idx,
                          global const float *w, const int taps, const int cols)
{
    const int c = get_global_id(0), i = get_global_id(1);
    const global int *ix = idx + (size_t)i * taps;
    const global float *wx = w + (size_t)i * taps;
    float s = 0.0f;
    for (int k = 0; k < taps; ++k)
        s += wx[k] * src[(size_t)ix[k] * cols + c];
    dst[(size_t)i * cols + c] = s;
}

kernel void multiply(global float *a, global const float *b)
{
    const int p = get_global_id(0);
    a[p] *= b[p];
}

// Veiling glare and vignetting: (s (1 - g) + halo g) gain, as Detector.spread ends.
kernel void glare_gain(global float *s, global const float *halo, global const float *gain, const float g)
{
    const int p = get_global_id(0);
    s[p] = (s[p] * (1.0f - g) + halo[p] * g) * gain[p];
}

kernel void gather(global const float *src, global const int *idx, global float *dst)
{
    const int i = get_global_id(0);
    dst[i] = src[idx[i]];
}

// The recursive filter: y = w y + (1 - w) x.
kernel void recursive(global float *state, global const float *x, const float w)
{
    const int p = get_global_id(0);
    state[p] = state[p] * w + (1.0f - w) * x[p];
}

// The log amplifier: -ln(max(signal, floor)).
kernel void neg_log(global const float *src, global float *dst, const float floor_)
{
    const int p = get_global_id(0);
    dst[p] = -log(fmax(src[p], floor_));
}

// Edge enhancement: p + amount (p - blurred p).
kernel void unsharp_mix(global float *p, global const float *blurred, const float amount)
{
    const int i = get_global_id(0);
    p[i] = p[i] + amount * (p[i] - blurred[i]);
}

// The window, display_lut.to_display's soft knee in closed form, the polarity and the edge:
// x = p scale + offset; c = x clipped to [k, 1 - k]; grey = c + k (x - c) / (k + |x - c|).
kernel void display(global const float *p, global const float *edge, global float *out, const float scale,
                    const float offset, const float knee, const int invert)
{
    const int i = get_global_id(0);
    const float x = p[i] * scale + offset;
    float grey;
    if (knee <= 0.0f) {
        grey = clamp(x, 0.0f, 1.0f);
    } else {
        const float c = clamp(x, knee, 1.0f - knee);
        const float s = x - c;
        grey = c + s * knee / (knee + fabs(s));
    }
    if (invert)
        grey = 1.0f - grey;
    out[i] = grey * edge[i];
}
