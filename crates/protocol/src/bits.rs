//! Bit-level writing and reading for the records of a state update (`docs/protocol.md`,
//! section 5.3): bits fill each byte from its least significant bit up, and a field of
//! `n` bits goes least significant bit first, so a field is its value's low `n` bits
//! wherever it starts. Exp-Golomb codes carry the ids.

use crate::error::DecodeError;

/// Appends bits to a byte slice. Fields gather in a 64-bit word, which goes to the slice
/// eight bytes at a time: a record is a dozen short fields, and reading and writing the
/// slice for each field was most of the cost of packing a datagram. The bits reach the
/// slice when the word fills and when the writer finishes ([`BitWriter::finish`]) or is
/// dropped.
pub(crate) struct BitWriter<'a> {
    out: &'a mut [u8],
    /// Bytes of `out` written.
    flushed: usize,
    /// Bits not in `out` yet, the first in the lowest bit.
    word: u64,
    /// How many bits `word` holds (below 64).
    held: u32,
}

impl<'a> BitWriter<'a> {
    /// A writer at the start of `out`, whose bytes it overwrites as far as it writes.
    pub(crate) fn new(out: &'a mut [u8]) -> Self {
        Self { out, flushed: 0, word: 0, held: 0 }
    }

    /// Writes the low `n` bits of `v` (`n` ≤ 64). The caller sized the slice: writing
    /// past its end panics, which `pack_deltas` rules out by measuring first.
    #[inline]
    pub(crate) fn put(&mut self, v: u64, n: u32) {
        if n == 0 {
            return;
        }
        let v = v & (u64::MAX >> (64 - n));
        self.word |= v << self.held;
        let total = self.held + n;
        if total < 64 {
            self.held = total;
            return;
        }
        // The word is full: out it goes, and the field's bits that did not fit start
        // the next (none when the word was empty).
        self.out[self.flushed..self.flushed + 8].copy_from_slice(&self.word.to_le_bytes());
        self.flushed += 8;
        self.word = v.checked_shr(64 - self.held).unwrap_or(0);
        self.held = total - 64;
    }

    /// Writes `v` in `n` bits, two's complement (the caller checked it fits).
    #[inline]
    pub(crate) fn put_signed(&mut self, v: i64, n: u32) {
        self.put(v as u64, n);
    }

    /// Writes `v` as an exp-Golomb code of order `k` ([`exp_golomb_bits`]).
    #[inline]
    pub(crate) fn put_exp_golomb(&mut self, v: u64, k: u32) {
        let w = u128::from(v) + (1u128 << k);
        let n = 127 - w.leading_zeros();
        // `n - k` zeros, a one, then the `n` bits of `w` below its top bit: one field
        // when they fit one (every id gap of a datagram does).
        let low = w - (1u128 << n);
        let zeros = n - k;
        if zeros + 1 + n <= 64 {
            self.put((1 | (low as u64) << 1) << zeros, zeros + 1 + n);
            return;
        }
        self.put(0, zeros);
        self.put(1, 1);
        self.put(low as u64, n.min(64));
        if n > 64 {
            self.put((low >> 64) as u64, n - 64);
        }
    }

    /// Bits written so far.
    #[cfg(test)]
    pub(crate) fn bits(&self) -> usize {
        self.flushed * 8 + self.held as usize
    }

    /// Puts the last bits into the slice (the last byte padded with zeros) and returns
    /// the bytes written.
    pub(crate) fn finish(mut self) -> usize {
        assert!(self.flush(), "the bits written overran the slice");
        self.flushed
    }

    /// Writes the bits held; false if the slice has no room for them (a caller's bug,
    /// which `finish` reports by panicking and a drop during a panic must not).
    fn flush(&mut self) -> bool {
        let tail = self.held.div_ceil(8) as usize;
        let Some(dst) = self.out.get_mut(self.flushed..self.flushed + tail) else { return false };
        dst.copy_from_slice(&self.word.to_le_bytes()[..tail]);
        self.flushed += tail;
        (self.word, self.held) = (0, 0);
        true
    }
}

impl Drop for BitWriter<'_> {
    /// A writer dropped unfinished still leaves every bit in the slice.
    fn drop(&mut self) {
        self.flush();
    }
}

/// Reads bits from a byte slice; every read checks the length first.
pub(crate) struct BitReader<'a> {
    bytes: &'a [u8],
    /// Bits read so far.
    at: usize,
}

impl<'a> BitReader<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, at: 0 }
    }

    fn truncated(&self, bits: u32) -> DecodeError {
        DecodeError::Truncated { needed: (self.at + bits as usize).div_ceil(8), got: self.bytes.len() }
    }

    /// The next 57 to 64 bits as one word (bit 0 the next), if 8 bytes are left from
    /// the current one.
    fn window(&self) -> Option<u64> {
        let byte = self.at / 8;
        let word = self.bytes.get(byte..byte + 8)?;
        Some(u64::from_le_bytes(word.try_into().ok()?) >> (self.at % 8))
    }

    /// Reads `n` bits (`n` ≤ 64) as an unsigned value.
    pub(crate) fn get(&mut self, n: u32) -> Result<u64, DecodeError> {
        if self.at + n as usize > self.bytes.len() * 8 {
            return Err(self.truncated(n));
        }
        if n <= 56
            && let Some(w) = self.window()
        {
            self.at += n as usize;
            return Ok(if n == 0 { 0 } else { w & (u64::MAX >> (64 - n)) });
        }
        let (mut v, mut got) = (0u64, 0u32);
        while got < n {
            let (byte, bit) = (self.at / 8, (self.at % 8) as u32);
            let take = (8 - bit).min(n - got);
            let part = u64::from(self.bytes[byte] >> bit) & ((1u64 << take) - 1);
            v |= part << got;
            got += take;
            self.at += take as usize;
        }
        Ok(v)
    }

    /// Reads `n` bits (1 ≤ `n` ≤ 32) as a two's complement value.
    pub(crate) fn get_signed(&mut self, n: u32) -> Result<i32, DecodeError> {
        let v = self.get(n)? as u32;
        let shift = 32 - n;
        Ok(((v << shift) as i32) >> shift)
    }

    /// Reads one bit.
    pub(crate) fn bit(&mut self) -> Result<bool, DecodeError> {
        Ok(self.get(1)? == 1)
    }

    /// Reads an exp-Golomb code of order `k`; a value past `u64::MAX` is malformed
    /// (every value has one code, so there is nothing else to check).
    pub(crate) fn get_exp_golomb(&mut self, k: u32) -> Result<u64, DecodeError> {
        // Fast path: the zeros and their one within the next 56 bits.
        let zeros = match self.window().map(|w| w & (u64::MAX >> 8)) {
            Some(w) if w != 0 => {
                let zeros = w.trailing_zeros();
                if zeros + k > 64 {
                    return Err(DecodeError::BadIdCode);
                }
                self.at += zeros as usize + 1;
                zeros
            }
            _ => self.count_zeros(k)?,
        };
        let n = zeros + k;
        let mut low = u128::from(self.get(n.min(64))?);
        if n > 64 {
            low |= u128::from(self.get(n - 64)?) << 64;
        }
        let v = (1u128 << n) + low - (1u128 << k);
        u64::try_from(v).map_err(|_| DecodeError::BadIdCode)
    }

    /// Counts the zeros of an exp-Golomb code of order `k` bit by bit, and reads its one.
    fn count_zeros(&mut self, k: u32) -> Result<u32, DecodeError> {
        let mut zeros = 0u32;
        while !self.bit()? {
            zeros += 1;
            // `w` below 2^65: no code of a u64 has more zeros than this.
            if zeros + k > 64 {
                return Err(DecodeError::BadIdCode);
            }
        }
        Ok(zeros)
    }

    /// Checks that what is left is the zero padding of the last byte.
    pub(crate) fn finish(self) -> Result<(), DecodeError> {
        let used = self.at.div_ceil(8);
        if used < self.bytes.len() {
            return Err(DecodeError::TrailingBytes { extra: self.bytes.len() - used });
        }
        let pad = (8 - self.at % 8) % 8;
        match self.bytes.last() {
            Some(&last) if pad > 0 && last >> (8 - pad) != 0 => Err(DecodeError::ReservedBits(u32::from(last))),
            _ => Ok(()),
        }
    }
}

/// Bits of the exp-Golomb code of order `k` of `v`: `n - k` zeros, a one and the `n`
/// bits below the top bit of `w = v + 2^k`, where `2^n ≤ w < 2^(n+1)`; so `2n - k + 1`.
pub(crate) fn exp_golomb_bits(v: u64, k: u32) -> u32 {
    let w = u128::from(v) + (1u128 << k);
    let n = 127 - w.leading_zeros();
    2 * n - k + 1
}

/// Bits a two's complement field needs to hold `v`.
pub(crate) fn signed_bits(v: i64) -> u32 {
    let magnitude = if v < 0 { !v } else { v };
    65 - magnitude.leading_zeros()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_and_codes_read_back_as_written() {
        let mut buf = [0u8; 256];
        let values = [0u64, 1, 2, 3, 7, 8, 511, 512, 1 << 40, u64::MAX - 1, u64::MAX];
        let mut w = BitWriter::new(&mut buf);
        for (i, &v) in values.iter().enumerate() {
            w.put(i as u64 % 8, 3);
            w.put_exp_golomb(v, (i as u32 * 7) % 64);
            w.put_signed(-(i as i64), 6);
        }
        let len = w.finish();
        let mut r = BitReader::new(&buf[..len]);
        for (i, &v) in values.iter().enumerate() {
            assert_eq!(r.get(3).unwrap(), i as u64 % 8);
            assert_eq!(r.get_exp_golomb((i as u32 * 7) % 64).unwrap(), v, "value {v}");
            assert_eq!(r.get_signed(6).unwrap(), -(i as i32));
        }
        r.finish().unwrap();
    }

    #[test]
    fn code_lengths_match_what_is_written() {
        for k in [0, 1, 5, 9, 33, 63] {
            for v in [0u64, 1, 2, 100, 1 << 20, u64::MAX] {
                let mut buf = [0u8; 32];
                let mut w = BitWriter::new(&mut buf);
                w.put_exp_golomb(v, k);
                assert_eq!(w.bits() as u32, exp_golomb_bits(v, k), "v {v} k {k}");
            }
        }
        assert_eq!(exp_golomb_bits(0, 0), 1);
        assert_eq!(exp_golomb_bits(1, 0), 3);
        assert_eq!(exp_golomb_bits(0, 9), 10);
        assert_eq!(signed_bits(0), 1);
        assert_eq!(signed_bits(-1), 1);
        assert_eq!(signed_bits(1), 2);
        assert_eq!(signed_bits(-2), 2);
        assert_eq!(signed_bits(511), 10);
        assert_eq!(signed_bits(-512), 10);
        assert_eq!(signed_bits(512), 11);
    }

    #[test]
    fn a_code_past_u64_max_and_bad_padding_are_malformed() {
        // 65 zeros after order 0: beyond any u64.
        let buf = [0u8; 16];
        assert_eq!(BitReader::new(&buf).get_exp_golomb(0), Err(DecodeError::BadIdCode));
        // Order 0 with 64 zeros, a one and 64 ones: 2^65 - 2, past u64::MAX.
        let mut buf = [0u8; 24];
        let mut w = BitWriter::new(&mut buf);
        w.put(0, 64);
        w.put(1, 1);
        w.put(u64::MAX, 64);
        w.finish();
        assert_eq!(BitReader::new(&buf).get_exp_golomb(0), Err(DecodeError::BadIdCode));
        // A set padding bit.
        let mut r = BitReader::new(&[0b1000_0001]);
        assert!(r.bit().unwrap());
        assert_eq!(r.finish(), Err(DecodeError::ReservedBits(0x81)));
        let mut r = BitReader::new(&[0b0000_0001, 0]);
        assert!(r.bit().unwrap());
        assert_eq!(r.finish(), Err(DecodeError::TrailingBytes { extra: 1 }));
        assert!(matches!(BitReader::new(&[1]).get(9), Err(DecodeError::Truncated { needed: 2, got: 1 })));
    }

    /// The word-at-a-time writer against one that sets bit after bit: fields of every
    /// width from 0 to 64 at every offset within the word, and codes long and short.
    #[test]
    fn the_writer_puts_each_bit_where_one_bit_at_a_time_would() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut buf = vec![0xAAu8; 16_384];
        let mut want = vec![0u8; 16_384];
        let mut at = 0usize;
        let mut set = |want: &mut Vec<u8>, v: u64, n: u32| {
            for b in 0..n {
                want[at / 8] |= (((v >> b) & 1) as u8) << (at % 8);
                at += 1;
            }
        };
        let mut w = BitWriter::new(&mut buf);
        for i in 0..1500u32 {
            let v = next();
            if i % 5 == 4 {
                let k = (next() % 12) as u32;
                let v = v >> (next() % 64);
                w.put_exp_golomb(v, k);
                let wide = u128::from(v) + (1u128 << k);
                let n = 127 - wide.leading_zeros();
                set(&mut want, 0, n - k);
                set(&mut want, 1, 1);
                let low = wide - (1u128 << n);
                set(&mut want, low as u64, n.min(64));
                set(&mut want, (low >> 64) as u64, n.saturating_sub(64));
            } else {
                let n = i % 65;
                w.put(v, n);
                set(&mut want, v, n);
            }
        }
        let bits = w.bits();
        let len = w.finish();
        assert_eq!(bits, at);
        assert_eq!(len, at.div_ceil(8));
        assert_eq!(buf[..len], want[..len]);
        assert_eq!(buf[len], 0xAA, "nothing past the last byte written");
    }
}
