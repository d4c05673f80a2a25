//! The values of one tensor of an update's payload under each [`UpdateEncoding`]: how many bytes they take, how
//! they are written, and how they are read back, refusing what an honest encoder cannot produce.
//!
//! Layouts (little-endian), for a tensor of `n` values:
//! - f32: `n` x `f32`;
//! - f16, bf16: `n` x `u16` (the value's bits);
//! - int8: per block of [`INT8_BLOCK`] values (the last one shorter), an `f32` scale then one `i8` per value in
//!   `[-127, 127]`; a value is `scale * q`;
//! - top-k: `u32` count `k` (at most `ceil(fraction * n)`), `k` x `u32` strictly increasing indices, `k` x `f32`
//!   values; every other value is 0.

use half::{bf16, f16};

use crate::error::CodecError;
use crate::protocol::{INT8_BLOCK, UpdateEncoding};
use crate::reader::Reader;

/// Bytes `values` of `numel` take under `encoding` (top-k at its full count).
pub(crate) fn encoded_len(encoding: UpdateEncoding, numel: usize) -> usize {
    match encoding {
        UpdateEncoding::F32 => 4 * numel,
        UpdateEncoding::F16 | UpdateEncoding::Bf16 => 2 * numel,
        UpdateEncoding::Int8 => numel + 4 * numel.div_ceil(INT8_BLOCK),
        UpdateEncoding::Topk { fraction } => 4 + 8 * UpdateEncoding::topk_count(fraction, numel),
    }
}

/// Appends `values` as `encoding` lays them out, and leaves in `values` what the reader will not get back (the
/// rounding error, or the values top-k left out): the residual top-k's error feedback carries to the next round.
pub(crate) fn write_values(encoding: UpdateEncoding, values: &mut [f32], out: &mut Vec<u8>) {
    match encoding {
        UpdateEncoding::F32 => {
            out.extend(values.iter().flat_map(|v| v.to_le_bytes()));
            values.fill(0.0);
        }
        UpdateEncoding::F16 => {
            for v in values {
                let h = f16::from_f32(*v);
                out.extend_from_slice(&h.to_bits().to_le_bytes());
                *v -= h.to_f32();
            }
        }
        UpdateEncoding::Bf16 => {
            for v in values {
                let h = bf16::from_f32(*v);
                out.extend_from_slice(&h.to_bits().to_le_bytes());
                *v -= h.to_f32();
            }
        }
        UpdateEncoding::Int8 => {
            for block in values.chunks_mut(INT8_BLOCK) {
                let absmax = block.iter().fold(0f32, |m, v| m.max(v.abs()));
                let scale = absmax / 127.0;
                out.extend_from_slice(&scale.to_le_bytes());
                for v in block {
                    let q = if scale > 0.0 { (*v / scale).round().clamp(-127.0, 127.0) as i8 } else { 0 };
                    out.push(q as u8);
                    *v -= scale * f32::from(q);
                }
            }
        }
        UpdateEncoding::Topk { fraction } => {
            let kept = largest(values, UpdateEncoding::topk_count(fraction, values.len()));
            out.extend_from_slice(&(kept.len() as u32).to_le_bytes());
            out.extend(kept.iter().flat_map(|&i| (i as u32).to_le_bytes()));
            out.extend(kept.iter().flat_map(|&i| values[i].to_le_bytes()));
            for &i in &kept {
                values[i] = 0.0;
            }
        }
    }
}

/// Appends every nonzero value of `values` in top-k's layout, so that [`read_values`] at a fraction of 1 reads them
/// back exactly: how a download sends a top-k run's change of the global model, as sparse as its clients' updates
/// (plain FedAvg's is their union), which top-k at the run's fraction would mostly drop.
pub(crate) fn write_nonzero(values: &[f32], out: &mut Vec<u8>) {
    let kept: Vec<usize> = (0..values.len()).filter(|&i| values[i] != 0.0).collect();
    out.extend_from_slice(&(kept.len() as u32).to_le_bytes());
    out.extend(kept.iter().flat_map(|&i| (i as u32).to_le_bytes()));
    out.extend(kept.iter().flat_map(|&i| values[i].to_le_bytes()));
}

/// Reads `numel` values laid out as `encoding`; `name` is for errors.
pub(crate) fn read_values(
    encoding: UpdateEncoding,
    numel: usize,
    r: &mut Reader<'_>,
    name: &str,
) -> Result<Vec<f32>, CodecError> {
    let overrun = || CodecError::Malformed(format!("tensor `{name}` of {numel} values overruns the payload"));
    let fixed = match encoding {
        UpdateEncoding::Topk { .. } => None,
        _ => Some(encoded_len(encoding, numel)),
    };
    if fixed.is_some_and(|len| len > r.remaining()) {
        return Err(overrun());
    }
    match encoding {
        UpdateEncoding::F32 => {
            Ok(r.bytes(4 * numel)?.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
        }
        UpdateEncoding::F16 => Ok(r
            .bytes(2 * numel)?
            .chunks_exact(2)
            .map(|b| f16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32())
            .collect()),
        UpdateEncoding::Bf16 => Ok(r
            .bytes(2 * numel)?
            .chunks_exact(2)
            .map(|b| bf16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32())
            .collect()),
        UpdateEncoding::Int8 => {
            let mut values = Vec::with_capacity(numel);
            let mut left = numel;
            while left > 0 {
                let len = left.min(INT8_BLOCK);
                let scale = f32::from_le_bytes(r.bytes(4)?.try_into().expect("4 bytes"));
                if !(scale.is_finite() && scale >= 0.0) {
                    return Err(CodecError::Malformed(format!("tensor `{name}` has an int8 block scale of {scale}")));
                }
                for &b in r.bytes(len)? {
                    let q = b as i8;
                    if q == i8::MIN {
                        return Err(CodecError::Malformed(format!(
                            "tensor `{name}` holds int8 -128 (range -127..=127)"
                        )));
                    }
                    values.push(scale * f32::from(q));
                }
                left -= len;
            }
            Ok(values)
        }
        UpdateEncoding::Topk { fraction } => {
            let k = r.u32()? as usize;
            let most = UpdateEncoding::topk_count(fraction, numel);
            if k > most {
                return Err(CodecError::Malformed(format!(
                    "tensor `{name}` sends {k} of {numel} values, top-k {fraction} allows {most}"
                )));
            }
            if k.checked_mul(8).is_none_or(|len| len > r.remaining()) {
                return Err(overrun());
            }
            let indices = r.bytes(4 * k)?;
            let kept = r.bytes(4 * k)?;
            let mut values = vec![0.0; numel];
            let mut next = 0usize;
            for (i, v) in indices.chunks_exact(4).zip(kept.chunks_exact(4)) {
                let i = u32::from_le_bytes([i[0], i[1], i[2], i[3]]) as usize;
                if i < next || i >= numel {
                    return Err(CodecError::Malformed(format!(
                        "tensor `{name}`'s top-k index {i} is out of order or out of its {numel} values"
                    )));
                }
                values[i] = f32::from_le_bytes([v[0], v[1], v[2], v[3]]);
                next = i + 1;
            }
            Ok(values)
        }
    }
}

/// Indices of the `k` values largest in magnitude, ascending (ties to the lower index, so the choice is
/// deterministic).
fn largest(values: &[f32], k: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    let by_magnitude = |&a: &usize, &b: &usize| values[b].abs().total_cmp(&values[a].abs()).then(a.cmp(&b));
    if k < order.len() {
        order.select_nth_unstable_by(k, by_magnitude);
        order.truncate(k);
    }
    order.sort_unstable();
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the writer says it sent (the values less what it left behind), what the reader read, and the bytes.
    fn round_trip(encoding: UpdateEncoding, values: &[f32]) -> (Vec<f32>, Vec<f32>, usize) {
        let mut out = Vec::new();
        let mut left = values.to_vec();
        write_values(encoding, &mut left, &mut out);
        let sent = values.iter().zip(&left).map(|(v, l)| v - l).collect();
        let mut r = Reader::new(&out);
        let read = read_values(encoding, values.len(), &mut r, "t").unwrap();
        assert_eq!(r.remaining(), 0);
        (sent, read, out.len())
    }

    fn ramp(n: usize) -> Vec<f32> {
        (0..n).map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5).collect()
    }

    #[test]
    fn each_encoding_reads_back_what_it_wrote_in_its_length() {
        let values = ramp(1000);
        for encoding in [
            UpdateEncoding::F32,
            UpdateEncoding::F16,
            UpdateEncoding::Bf16,
            UpdateEncoding::Int8,
            UpdateEncoding::Topk { fraction: 0.01 },
        ] {
            let (sent, read, len) = round_trip(encoding, &values);
            assert_eq!(sent, read, "{encoding:?}");
            assert_eq!(len, encoded_len(encoding, values.len()), "{encoding:?}");
        }
        assert_eq!(round_trip(UpdateEncoding::F32, &values).1, values);
    }

    #[test]
    fn rounding_stays_within_each_encodings_bound() {
        let values: Vec<f32> = ramp(700).iter().enumerate().map(|(i, v)| v * (1 + i / 256) as f32).collect();
        let (_, f16s, _) = round_trip(UpdateEncoding::F16, &values);
        let (_, bf16s, _) = round_trip(UpdateEncoding::Bf16, &values);
        for ((v, h), b) in values.iter().zip(&f16s).zip(&bf16s) {
            assert!((v - h).abs() <= v.abs() * 2f32.powi(-11) + 1e-7, "f16 {v} -> {h}");
            assert!((v - b).abs() <= v.abs() * 2f32.powi(-8), "bf16 {v} -> {b}");
        }
        let (_, int8s, _) = round_trip(UpdateEncoding::Int8, &values);
        for (block, read) in values.chunks(INT8_BLOCK).zip(int8s.chunks(INT8_BLOCK)) {
            let absmax = block.iter().fold(0f32, |m, v| m.max(v.abs()));
            for (v, q) in block.iter().zip(read) {
                assert!((v - q).abs() <= absmax / 254.0 * (1.0 + 1e-5), "int8 {v} -> {q} (absmax {absmax})");
            }
        }
    }

    #[test]
    fn topk_keeps_the_largest_magnitudes_and_zeroes_the_rest() {
        let values = [0.1, -5.0, 0.2, 3.0, -0.3, 3.0, 0.0, 1.0];
        let (sent, _, len) = round_trip(UpdateEncoding::Topk { fraction: 0.3 }, &values);
        // ceil(0.3 * 8) = 3: -5 and both 3s.
        assert_eq!(sent, [0.0, -5.0, 0.0, 3.0, 0.0, 3.0, 0.0, 0.0]);
        assert_eq!(len, 4 + 8 * 3);
        let (all, _, _) = round_trip(UpdateEncoding::Topk { fraction: 1.0 }, &values);
        assert_eq!(all, values);
        assert_eq!(UpdateEncoding::topk_count(1e-9, 5), 1);
        assert_eq!(UpdateEncoding::topk_count(0.5, 0), 0);

        let mut out = Vec::new();
        write_nonzero(&values, &mut out);
        assert_eq!(out.len(), 4 + 8 * 7, "every value but the 0");
        let read = read_values(UpdateEncoding::Topk { fraction: 1.0 }, values.len(), &mut Reader::new(&out), "t");
        assert_eq!(read.unwrap(), values);
    }

    #[test]
    fn refuses_what_no_encoder_writes() {
        let read = |encoding, numel, bytes: &[u8]| read_values(encoding, numel, &mut Reader::new(bytes), "t");
        let topk = UpdateEncoding::Topk { fraction: 0.5 };
        let pairs = |k: u32, idx: &[u32]| {
            let mut b = k.to_le_bytes().to_vec();
            b.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
            b.extend(idx.iter().flat_map(|_| 1f32.to_le_bytes()));
            b
        };
        assert!(read(topk, 4, &pairs(2, &[0, 3])).is_ok());
        assert!(
            matches!(read(topk, 4, &pairs(3, &[0, 1, 2])), Err(CodecError::Malformed(m)) if m.contains("allows 2"))
        );
        assert!(
            matches!(read(topk, 4, &pairs(2, &[3, 1])), Err(CodecError::Malformed(m)) if m.contains("out of order"))
        );
        assert!(matches!(read(topk, 4, &pairs(2, &[1, 1])), Err(CodecError::Malformed(_))));
        assert!(matches!(read(topk, 4, &pairs(1, &[4])), Err(CodecError::Malformed(_))));
        assert!(matches!(read(topk, 4, &pairs(2, &[0, 1])[..12]), Err(CodecError::Malformed(_))));

        let int8 = |scale: f32, q: u8| {
            let mut b = scale.to_le_bytes().to_vec();
            b.push(q);
            b
        };
        assert_eq!(read(UpdateEncoding::Int8, 1, &int8(0.5, 2)).unwrap(), [1.0]);
        assert!(read(UpdateEncoding::Int8, 1, &int8(f32::NAN, 2)).is_err());
        assert!(read(UpdateEncoding::Int8, 1, &int8(-1.0, 2)).is_err());
        assert!(read(UpdateEncoding::Int8, 1, &int8(1.0, 0x80)).is_err());
        assert!(read(UpdateEncoding::Int8, 2, &int8(1.0, 1)).is_err());
        assert!(read(UpdateEncoding::F16, 2, &[0, 0, 0]).is_err());
    }
}
