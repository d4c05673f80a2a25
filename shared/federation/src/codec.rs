//! Binary update codec: [`NamedTensors`] <-> payload <-> frames.
//!
//! Payload (little-endian): `u32` tensor count, then per tensor in name order `u32` name length, UTF-8 name,
//! `u32` rank, `u64` per dimension, and the `f32` values.
//!
//! Each binary WebSocket frame is a [`FrameHeader`] of [`HEADER_LEN`] bytes followed by one chunk of the payload:
//! magic `FVLA`, `u16` protocol version, `u64` round, `u32` chunk index, `u32` chunk count, `u64` payload length,
//! `u32` CRC32 of the whole payload, `u32` chunk length.

use crate::error::CodecError;
use crate::protocol::PROTOCOL_VERSION;
use crate::tensors::{NamedTensors, TensorSpec};

pub const MAGIC: [u8; 4] = *b"FVLA";
pub const HEADER_LEN: usize = 38;
/// Default frame size limit: 1 MiB including the header.
pub const DEFAULT_MAX_FRAME_BYTES: usize = 1 << 20;
/// Ranks above this are refused as malformed.
const MAX_RANK: usize = 8;

/// The header in front of every binary frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameHeader {
    pub protocol_version: u16,
    pub round: u64,
    pub chunk_index: u32,
    pub chunk_count: u32,
    pub payload_len: u64,
    pub crc32: u32,
    pub chunk_len: u32,
}

impl FrameHeader {
    pub fn write(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&self.protocol_version.to_le_bytes());
        out.extend_from_slice(&self.round.to_le_bytes());
        out.extend_from_slice(&self.chunk_index.to_le_bytes());
        out.extend_from_slice(&self.chunk_count.to_le_bytes());
        out.extend_from_slice(&self.payload_len.to_le_bytes());
        out.extend_from_slice(&self.crc32.to_le_bytes());
        out.extend_from_slice(&self.chunk_len.to_le_bytes());
    }

    /// Parses the header at the start of `frame`, checking magic and protocol version.
    pub fn parse(frame: &[u8]) -> Result<Self, CodecError> {
        let mut r = Reader::new(frame);
        if r.bytes(4)? != MAGIC {
            return Err(CodecError::BadMagic);
        }
        let protocol_version = r.u16()?;
        if protocol_version != PROTOCOL_VERSION {
            return Err(CodecError::ProtocolVersion { expected: PROTOCOL_VERSION, got: protocol_version });
        }
        Ok(Self {
            protocol_version,
            round: r.u64()?,
            chunk_index: r.u32()?,
            chunk_count: r.u32()?,
            payload_len: r.u64()?,
            crc32: r.u32()?,
            chunk_len: r.u32()?,
        })
    }
}

/// Length of the payload [`encode_payload`] makes for tensors of this spec.
pub fn payload_len(spec: &TensorSpec) -> usize {
    4 + spec.iter().map(|(name, shape)| 4 + name.len() + 4 + 8 * shape.len()).sum::<usize>() + spec.byte_size()
}

pub fn encode_payload(tensors: &NamedTensors) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload_len(&tensors.spec()));
    out.extend_from_slice(&(tensors.len() as u32).to_le_bytes());
    for (name, t) in tensors.iter() {
        out.extend_from_slice(&(name.len() as u32).to_le_bytes());
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(&(t.shape.len() as u32).to_le_bytes());
        for &d in &t.shape {
            out.extend_from_slice(&(d as u64).to_le_bytes());
        }
        for v in &t.values {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Parses a payload and validates it against `spec` (names, shapes, finite values).
pub fn decode_payload(payload: &[u8], spec: &TensorSpec) -> Result<NamedTensors, CodecError> {
    let mut r = Reader::new(payload);
    let count = r.u32()? as usize;
    let mut out = NamedTensors::new();
    for _ in 0..count {
        let name_len = r.u32()? as usize;
        let name = std::str::from_utf8(r.bytes(name_len)?)
            .map_err(|_| CodecError::Malformed("tensor name is not UTF-8".into()))?
            .to_owned();
        let rank = r.u32()? as usize;
        if rank > MAX_RANK {
            return Err(CodecError::Malformed(format!("tensor `{name}` has rank {rank} (max {MAX_RANK})")));
        }
        let shape = (0..rank).map(|_| r.u64().map(|d| d as usize)).collect::<Result<Vec<_>, _>>()?;
        let numel = shape
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
            .filter(|n| n.checked_mul(4).is_some_and(|b| b <= r.remaining()))
            .ok_or_else(|| CodecError::Malformed(format!("tensor `{name}` of shape {shape:?} overruns the payload")))?;
        let values =
            r.bytes(numel * 4)?.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        if out.get(&name).is_some() {
            return Err(CodecError::Malformed(format!("tensor `{name}` appears twice")));
        }
        out.insert(name, shape, values)?;
    }
    if r.remaining() != 0 {
        return Err(CodecError::Malformed(format!("{} trailing bytes after the last tensor", r.remaining())));
    }
    out.validate(spec)?;
    Ok(out)
}

/// Splits an encoded payload into frames of at most `max_frame_bytes` (header included).
pub fn encode_frames(payload: &[u8], round: u64, max_frame_bytes: usize) -> Vec<Vec<u8>> {
    assert!(max_frame_bytes > HEADER_LEN, "frame limit must exceed the {HEADER_LEN}-byte header");
    let chunk = max_frame_bytes - HEADER_LEN;
    let crc32 = crc32fast::hash(payload);
    let chunks: Vec<&[u8]> = if payload.is_empty() { vec![&[][..]] } else { payload.chunks(chunk).collect() };
    let chunk_count = chunks.len() as u32;
    chunks
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let mut frame = Vec::with_capacity(HEADER_LEN + c.len());
            FrameHeader {
                protocol_version: PROTOCOL_VERSION,
                round,
                chunk_index: i as u32,
                chunk_count,
                payload_len: payload.len() as u64,
                crc32,
                chunk_len: c.len() as u32,
            }
            .write(&mut frame);
            frame.extend_from_slice(c);
            frame
        })
        .collect()
}

/// Encodes tensors straight to frames.
pub fn encode_update(tensors: &NamedTensors, round: u64, max_frame_bytes: usize) -> Vec<Vec<u8>> {
    encode_frames(&encode_payload(tensors), round, max_frame_bytes)
}

/// Limits the receiving side enforces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UpdateLimits {
    pub max_frame_bytes: usize,
    pub max_payload_bytes: u64,
}

impl UpdateLimits {
    /// Limits for updates of `spec`: the exact payload plus `headroom` bytes (so an extra tensor is reported as
    /// unexpected rather than oversized).
    pub fn for_spec(spec: &TensorSpec, max_frame_bytes: usize, headroom: u64) -> Self {
        Self { max_frame_bytes, max_payload_bytes: payload_len(spec) as u64 + headroom }
    }
}

/// Reassembles frames of one update, in order, into its payload.
#[derive(Debug)]
pub struct Reassembler {
    limits: UpdateLimits,
    first: FrameHeader,
    payload: Vec<u8>,
    next_index: u32,
}

impl Reassembler {
    /// Starts from the first frame of an update.
    pub fn start(frame: &[u8], limits: UpdateLimits) -> Result<Self, CodecError> {
        let header = Self::check_frame(frame, &limits)?;
        if header.chunk_index != 0 {
            return Err(CodecError::Malformed(format!("update starts at chunk {}, expected 0", header.chunk_index)));
        }
        if header.chunk_count == 0 {
            return Err(CodecError::Malformed("chunk count is 0".into()));
        }
        if header.payload_len > limits.max_payload_bytes {
            return Err(CodecError::Oversized { len: header.payload_len, limit: limits.max_payload_bytes });
        }
        let mut r =
            Self { limits, first: header, payload: Vec::with_capacity(header.payload_len as usize), next_index: 0 };
        r.append(header, frame)?;
        Ok(r)
    }

    pub fn header(&self) -> &FrameHeader {
        &self.first
    }

    /// Whether every chunk has arrived.
    pub fn is_complete(&self) -> bool {
        self.next_index == self.first.chunk_count
    }

    /// Adds the next frame.
    pub fn push(&mut self, frame: &[u8]) -> Result<(), CodecError> {
        let header = Self::check_frame(frame, &self.limits)?;
        let first = &self.first;
        if (header.round, header.chunk_count, header.payload_len, header.crc32)
            != (first.round, first.chunk_count, first.payload_len, first.crc32)
        {
            return Err(CodecError::Malformed("frame header disagrees with the first frame of the update".into()));
        }
        self.append(header, frame)
    }

    /// The checked payload, once complete.
    pub fn finish(self) -> Result<Vec<u8>, CodecError> {
        if !self.is_complete() {
            return Err(CodecError::Malformed(format!(
                "update ended after {} of {} chunks",
                self.next_index, self.first.chunk_count
            )));
        }
        if self.payload.len() as u64 != self.first.payload_len {
            return Err(CodecError::Truncated { needed: self.first.payload_len as usize, got: self.payload.len() });
        }
        let got = crc32fast::hash(&self.payload);
        if got != self.first.crc32 {
            return Err(CodecError::ChecksumMismatch { expected: self.first.crc32, got });
        }
        Ok(self.payload)
    }

    fn check_frame(frame: &[u8], limits: &UpdateLimits) -> Result<FrameHeader, CodecError> {
        if frame.len() > limits.max_frame_bytes {
            return Err(CodecError::FrameTooLarge { len: frame.len(), limit: limits.max_frame_bytes });
        }
        let header = FrameHeader::parse(frame)?;
        if frame.len() != HEADER_LEN + header.chunk_len as usize {
            return Err(CodecError::Malformed(format!(
                "frame holds {} payload bytes, header says {}",
                frame.len().saturating_sub(HEADER_LEN),
                header.chunk_len
            )));
        }
        Ok(header)
    }

    fn append(&mut self, header: FrameHeader, frame: &[u8]) -> Result<(), CodecError> {
        if header.chunk_index != self.next_index {
            return Err(CodecError::Malformed(format!(
                "chunk {} arrived, expected {}",
                header.chunk_index, self.next_index
            )));
        }
        let total = self.payload.len() as u64 + header.chunk_len as u64;
        if total > self.first.payload_len {
            return Err(CodecError::Malformed("chunks exceed the announced payload length".into()));
        }
        self.payload.extend_from_slice(&frame[HEADER_LEN..]);
        self.next_index += 1;
        Ok(())
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn new(buf: &'a [u8]) -> Self {
        Self { buf, pos: 0 }
    }

    fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    fn bytes(&mut self, n: usize) -> Result<&'a [u8], CodecError> {
        if self.remaining() < n {
            return Err(CodecError::Truncated { needed: self.pos + n, got: self.buf.len() });
        }
        let out = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(out)
    }

    fn u16(&mut self) -> Result<u16, CodecError> {
        Ok(u16::from_le_bytes(self.bytes(2)?.try_into().expect("2 bytes")))
    }

    fn u32(&mut self) -> Result<u32, CodecError> {
        Ok(u32::from_le_bytes(self.bytes(4)?.try_into().expect("4 bytes")))
    }

    fn u64(&mut self) -> Result<u64, CodecError> {
        Ok(u64::from_le_bytes(self.bytes(8)?.try_into().expect("8 bytes")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::TensorError;
    use crate::protocol::ErrorCode;

    fn tensors() -> NamedTensors {
        let mut t = NamedTensors::new();
        t.insert("expert.w", vec![3, 50], (0..150).map(|i| i as f32 * 0.25).collect()).unwrap();
        t.insert("expert.b", vec![3], vec![1.0, 2.0, 3.0]).unwrap();
        t
    }

    fn limits(spec: &TensorSpec) -> UpdateLimits {
        UpdateLimits::for_spec(spec, 100, 64)
    }

    fn reassemble(frames: &[Vec<u8>], limits: UpdateLimits) -> Result<Vec<u8>, CodecError> {
        let mut r = Reassembler::start(&frames[0], limits)?;
        for f in &frames[1..] {
            r.push(f)?;
        }
        r.finish()
    }

    #[test]
    fn round_trip_over_many_small_frames() {
        let t = tensors();
        let frames = encode_update(&t, 7, 100);
        assert!(frames.len() > 5);
        assert!(frames.iter().all(|f| f.len() <= 100));
        let payload_bytes: usize = frames.iter().map(|f| f.len() - HEADER_LEN).sum();
        assert_eq!(payload_bytes, payload_len(&t.spec()));
        let payload = reassemble(&frames, limits(&t.spec())).unwrap();
        assert_eq!(decode_payload(&payload, &t.spec()).unwrap(), t);
        assert_eq!(FrameHeader::parse(&frames[0]).unwrap().round, 7);
    }

    #[test]
    fn refuses_bad_frames() {
        let t = tensors();
        let spec = t.spec();
        let frames = encode_update(&t, 1, 100);

        let mut bad_magic = frames[0].clone();
        bad_magic[0] = b'X';
        assert_eq!(Reassembler::start(&bad_magic, limits(&spec)).unwrap_err(), CodecError::BadMagic);

        let mut version = frames[0].clone();
        version[4..6].copy_from_slice(&(PROTOCOL_VERSION + 1).to_le_bytes());
        let err = Reassembler::start(&version, limits(&spec)).unwrap_err();
        assert_eq!(err.code(), ErrorCode::ProtocolVersion);

        let err = Reassembler::start(&frames[0][..10], limits(&spec)).unwrap_err();
        assert_eq!(err.code(), ErrorCode::MalformedFrame);

        let mut reordered = frames.clone();
        reordered.swap(1, 2);
        assert_eq!(reassemble(&reordered, limits(&spec)).unwrap_err().code(), ErrorCode::MalformedFrame);

        let mut flipped = frames.clone();
        let last = flipped.last_mut().unwrap();
        *last.last_mut().unwrap() ^= 1;
        assert!(matches!(reassemble(&flipped, limits(&spec)), Err(CodecError::ChecksumMismatch { .. })));

        let small = UpdateLimits { max_frame_bytes: 100, max_payload_bytes: 10 };
        assert_eq!(Reassembler::start(&frames[0], small).unwrap_err().code(), ErrorCode::Oversized);
        let tiny_frames = UpdateLimits { max_frame_bytes: 50, max_payload_bytes: 1 << 20 };
        assert!(matches!(Reassembler::start(&frames[0], tiny_frames), Err(CodecError::FrameTooLarge { .. })));
    }

    #[test]
    fn refuses_bad_tensors() {
        let t = tensors();
        let spec = t.spec();
        let mut nan = t.clone();
        nan.get_mut("expert.w").unwrap().values[3] = f32::INFINITY;
        let err = decode_payload(&encode_payload(&nan), &spec).unwrap_err();
        assert_eq!(err, CodecError::Tensor(TensorError::NonFinite { name: "expert.w".into(), index: 3 }));

        let mut extra = t.clone();
        extra.insert("vision.frozen", vec![1], vec![0.0]).unwrap();
        assert_eq!(decode_payload(&encode_payload(&extra), &spec).unwrap_err().code(), ErrorCode::UnexpectedTensor);

        let mut payload = encode_payload(&t);
        payload.push(0);
        assert_eq!(decode_payload(&payload, &spec).unwrap_err().code(), ErrorCode::MalformedFrame);
        let payload = encode_payload(&t);
        assert!(matches!(decode_payload(&payload[..payload.len() - 1], &spec), Err(CodecError::Malformed(_))));
    }
}
