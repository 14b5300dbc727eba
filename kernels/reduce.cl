/* Final stage of the reductions: out[slot] = sum_g partials[slot * groups + g] (groups = the
 * stride of the partials buffer).
 * One work-group per slot; global size = slots * local size.  Kahan per work-item, then a tree. */
__kernel void reduce_partials(__global const real_t *partials, __global real_t *out,
                              const int groups, __local real_t *scratch) {
    const int slot = get_group_id(0);
    real_t s = 0, c = 0;
    for (int g = get_local_id(0); g < groups; g += get_local_size(0))
        kahan_add(&s, &c, partials[(size_t)slot * groups + g]);
    const real_t t = group_sum(s, scratch);
    if (get_local_id(0) == 0) out[slot] = t;
}
