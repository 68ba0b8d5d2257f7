//! A parallel least-significant-digit radix sort of `(u64 key, u32 value)` pairs.
//!
//! Eight bits per pass. Each pass splits the input into chunks, counts digits per chunk
//! in parallel, turns the counts into per-(digit, chunk) output offsets with one prefix
//! sum, and scatters each chunk in parallel to its own offsets. The sort is stable, so
//! equal keys keep the order of their values as given (ascending object index when the
//! caller fills values with `0..n`), which makes the result unique and deterministic.
//! Passes whose digit is the same for every key are skipped.
//!
//! This is the same structure as the GPU sort (per-block histograms, a scan, a scatter).

use rayon::prelude::*;

use crate::par::SharedMut;

const RADIX_BITS: u32 = 8;
const BUCKETS: usize = 1 << RADIX_BITS;
/// Below this many items one thread sorts: splitting costs more than it saves.
const PARALLEL_MIN: usize = 1 << 14;

/// Sorts `keys` ascending, permuting `values` alongside; only the low `key_bits` bits of
/// the keys are looked at. `scratch_*` are reused buffers (resized as needed).
pub fn sort_pairs(
    keys: &mut Vec<u64>,
    values: &mut Vec<u32>,
    key_bits: u32,
    scratch_keys: &mut Vec<u64>,
    scratch_values: &mut Vec<u32>,
) {
    let n = keys.len();
    assert_eq!(n, values.len(), "one value per key");
    if n < 2 {
        return;
    }
    scratch_keys.resize(n, 0);
    scratch_values.resize(n, 0);
    let chunks = if n < PARALLEL_MIN { 1 } else { rayon::current_num_threads() * 4 };
    let chunk_len = n.div_ceil(chunks);
    let passes = key_bits.div_ceil(RADIX_BITS);
    for pass in 0..passes {
        let shift = pass * RADIX_BITS;
        let digit = |k: u64| ((k >> shift) as usize) & (BUCKETS - 1);
        let counts: Vec<[u32; BUCKETS]> = keys
            .par_chunks(chunk_len)
            .map(|c| {
                let mut h = [0u32; BUCKETS];
                for &k in c {
                    h[digit(k)] += 1;
                }
                h
            })
            .collect();
        // Skip a pass in which every key has the same digit: it would copy in order.
        let first = digit(keys[0]);
        if counts.iter().map(|h| h[first] as usize).sum::<usize>() == n {
            continue;
        }
        // offsets[chunk][digit]: where this chunk's keys with this digit start.
        let mut offsets = vec![[0u32; BUCKETS]; counts.len()];
        let mut running = 0u32;
        for d in 0..BUCKETS {
            for (c, h) in counts.iter().enumerate() {
                offsets[c][d] = running;
                running += h[d];
            }
        }
        {
            let out_k = SharedMut::new(scratch_keys);
            let out_v = SharedMut::new(scratch_values);
            keys.par_chunks(chunk_len).zip(values.par_chunks(chunk_len)).zip(offsets.par_iter_mut()).for_each(
                |((ks, vs), off)| {
                    for (&k, &v) in ks.iter().zip(vs) {
                        let d = digit(k);
                        let at = off[d] as usize;
                        off[d] += 1;
                        // SAFETY: the prefix sum gives every (chunk, digit) its own range
                        // of output positions, and this chunk advances only its own.
                        unsafe {
                            out_k.write(at, k);
                            out_v.write(at, v);
                        }
                    }
                },
            );
        }
        std::mem::swap(keys, scratch_keys);
        std::mem::swap(values, scratch_values);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::rng::Stream;

    fn check(mut keys: Vec<u64>, bits: u32) {
        let mut values: Vec<u32> = (0..keys.len() as u32).collect();
        let mut expected: Vec<(u64, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
        expected.sort(); // by key, then by original index: what a stable sort gives
        sort_pairs(&mut keys, &mut values, bits, &mut Vec::new(), &mut Vec::new());
        let got: Vec<(u64, u32)> = keys.into_iter().zip(values).collect();
        assert_eq!(got, expected);
    }

    #[test]
    fn sorts_like_a_stable_sort() {
        let mut s = Stream::new(1, 1);
        check((0..100_000).map(|_| s.next_u64() >> 1).collect(), 63);
        check((0..50_000).map(|_| s.next_u64() % 7).collect(), 63); // many duplicates
        check((0..1_000).map(|_| s.next_u64() & 0xffff).collect(), 16);
        check(vec![5; 40_000], 63);
        check(vec![], 63);
        check(vec![3], 63);
    }
}
