//! Binary update codec: [`NamedTensors`] <-> payload <-> frames.
//!
//! Payload (little-endian): `u8` encoding (0 f32, 1 f16, 2 bf16, 3 int8, 4 top-k: the task's
//! [`UpdateEncoding`]), `u32` tensor count, then per tensor in name order `u32` name length, UTF-8 name, `u32` rank,
//! `u64` per dimension, and its values as [`crate::quantize`] lays them out. An f32 payload holds the trained
//! tensors; every other encoding holds their delta from the round's global model.
//!
//! Each binary WebSocket frame is a [`FrameHeader`] of [`HEADER_LEN`] bytes followed by one chunk of the payload:
//! magic `FVLA`, `u16` protocol version, `u64` round, `u32` chunk index, `u32` chunk count, `u64` payload length,
//! `u32` CRC32 of the whole payload, `u32` chunk length.
//!
//! Downloads of the global model by a client that holds an earlier version come as a chain of the rounds' deltas
//! ([`encode_model_delta`], [`encode_model_deltas`], [`apply_model_deltas`]), each one such a payload.

use crate::error::{CodecError, TensorError};
use crate::protocol::{PROTOCOL_VERSION, UpdateEncoding};
use crate::quantize::{encoded_len, read_values, write_nonzero, write_values};
use crate::reader::Reader;
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

/// What a decoded update holds.
#[derive(Debug, Clone, PartialEq)]
pub enum UpdateValues {
    /// The trained tensors (f32 payloads).
    Model(NamedTensors),
    /// The trained tensors' delta from the round's global model (every compressed encoding).
    Delta(NamedTensors),
}

impl UpdateValues {
    /// The trained tensors: the model itself, or `global + delta`, checked finite (a finite delta added to a
    /// finite model can still overflow).
    pub fn into_model(self, global: &NamedTensors) -> Result<NamedTensors, TensorError> {
        match self {
            Self::Model(model) => Ok(model),
            Self::Delta(delta) => {
                let model = global.zip_map(&delta, |g, d| g + d)?;
                model.validate(&global.spec())?;
                Ok(model)
            }
        }
    }
}

fn encoding_tag(encoding: UpdateEncoding) -> u8 {
    match encoding {
        UpdateEncoding::F32 => 0,
        UpdateEncoding::F16 => 1,
        UpdateEncoding::Bf16 => 2,
        UpdateEncoding::Int8 => 3,
        UpdateEncoding::Topk { .. } => 4,
    }
}

/// Length of the payload of tensors of this spec under `encoding` (top-k at its full count per tensor): what the
/// server accepts at most.
pub fn payload_len(spec: &TensorSpec, encoding: UpdateEncoding) -> usize {
    1 + 4
        + spec
            .iter()
            .map(|(name, shape)| 4 + name.len() + 4 + 8 * shape.len() + encoded_len(encoding, shape.iter().product()))
            .sum::<usize>()
}

fn write_tensor_header(out: &mut Vec<u8>, name: &str, shape: &[usize]) {
    out.extend_from_slice(&(name.len() as u32).to_le_bytes());
    out.extend_from_slice(name.as_bytes());
    out.extend_from_slice(&(shape.len() as u32).to_le_bytes());
    for &d in shape {
        out.extend_from_slice(&(d as u64).to_le_bytes());
    }
}

/// The f32 payload of trained tensors.
pub fn encode_payload(tensors: &NamedTensors) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload_len(&tensors.spec(), UpdateEncoding::F32));
    out.push(encoding_tag(UpdateEncoding::F32));
    out.extend_from_slice(&(tensors.len() as u32).to_le_bytes());
    for (name, t) in tensors.iter() {
        write_tensor_header(&mut out, name, &t.shape);
        for v in &t.values {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// The payload of a delta from the round's global model under a compressed `encoding`, leaving in `delta` what
/// the server will not get back (top-k's error feedback carries it to the next round).
///
/// # Panics
/// On [`UpdateEncoding::F32`], whose payloads hold the trained tensors ([`encode_payload`]).
pub fn encode_delta_payload(delta: &mut NamedTensors, encoding: UpdateEncoding) -> Vec<u8> {
    assert!(encoding != UpdateEncoding::F32, "f32 updates carry the trained tensors, not a delta");
    let spec = delta.spec();
    let mut out = Vec::with_capacity(payload_len(&spec, encoding));
    out.push(encoding_tag(encoding));
    out.extend_from_slice(&(delta.len() as u32).to_le_bytes());
    for ((name, shape), (_, values)) in spec.iter().zip(delta.iter_mut()) {
        write_tensor_header(&mut out, name, shape);
        write_values(encoding, values, &mut out);
    }
    out
}

/// Parses a payload of the run's `encoding` and validates it against `spec` (names, shapes, finite values).
pub fn decode_payload(payload: &[u8], spec: &TensorSpec, encoding: UpdateEncoding) -> Result<UpdateValues, CodecError> {
    let mut r = Reader::new(payload);
    let tag = r.u8()?;
    if tag != encoding_tag(encoding) {
        return Err(CodecError::Malformed(format!(
            "update encoded as {}, the run asks for {} ({})",
            tag,
            encoding_tag(encoding),
            encoding.name()
        )));
    }
    let count = r.u32()? as usize;
    let mut out = NamedTensors::new();
    for _ in 0..count {
        let name_len = r.u32()? as usize;
        let name = std::str::from_utf8(r.bytes(name_len)?)
            .map_err(|_| CodecError::Malformed("tensor name is not UTF-8".into()))?
            .to_owned();
        // Only the spec's tensors, each once, are kept while the rest is read: what a payload makes the reader
        // hold is at most the spec's size, however many (empty) tensors it claims.
        let Some(expected) = spec.shape(&name) else {
            return Err(CodecError::Tensor(TensorError::Unexpected(name)));
        };
        if out.get(&name).is_some() {
            return Err(CodecError::Malformed(format!("tensor `{name}` appears twice")));
        }
        let rank = r.u32()? as usize;
        if rank > MAX_RANK {
            return Err(CodecError::Malformed(format!("tensor `{name}` has rank {rank} (max {MAX_RANK})")));
        }
        let shape = (0..rank).map(|_| r.u64().map(|d| d as usize)).collect::<Result<Vec<_>, _>>()?;
        // Every tensor of the spec is at most the spec's size: a larger shape is refused before it is allocated.
        let numel = shape
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
            .filter(|&n| n <= expected.iter().product())
            .ok_or_else(|| {
                CodecError::Tensor(TensorError::ShapeMismatch {
                    name: name.clone(),
                    expected: expected.to_vec(),
                    got: shape.clone(),
                })
            })?;
        let values = read_values(encoding, numel, &mut r, &name)?;
        out.insert(name, shape, values)?;
    }
    if r.remaining() != 0 {
        return Err(CodecError::Malformed(format!("{} trailing bytes after the last tensor", r.remaining())));
    }
    out.validate(spec)?;
    Ok(match encoding {
        UpdateEncoding::F32 => UpdateValues::Model(out),
        _ => UpdateValues::Delta(out),
    })
}

/// The encoding a download's delta payload of tag `tag` is read in: top-k's holds every value it sends, so it is read
/// at a fraction of 1. f32 is no delta encoding of downloads.
fn model_delta_encoding(tag: u8) -> Result<UpdateEncoding, CodecError> {
    if tag == encoding_tag(UpdateEncoding::F32) {
        return Err(CodecError::Malformed("a model delta in f32: f32 runs serve the model whole".into()));
    }
    [UpdateEncoding::F16, UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 1.0 }]
        .into_iter()
        .find(|e| encoding_tag(*e) == tag)
        .ok_or_else(|| CodecError::Malformed(format!("unknown encoding tag {tag}")))
}

/// The payload a download serves of the change from the global model `old` to the round's aggregate `new`, under the
/// run's update `encoding`, and the model a client holding `old` rebuilds from it: `old` plus the decoded payload,
/// value by value in f32 ([`UpdateValues::into_model`]). The server makes that model its next global model, so a
/// client that applies the payload ends up with the server's model bit for bit, natively as in wasm: the decoders'
/// conversions and IEEE f32 adds give the same bits everywhere, and the server's model is made by the same code
/// from the same bytes (decoding what it serves rather than reusing the values it encoded). For f16, bf16 and int8
/// this is a server-side quantization of the global update, within the encoding's bound of each round's change; for
/// top-k the payload holds every nonzero value of the change exactly ([`write_nonzero`]: top-k of an aggregate
/// would drop most of it for good) and the model is `old + (new - old)`, within an ulp of `new`.
///
/// `Ok(None)` for f32: its delta is as large as the model, which f32 runs serve whole, their aggregate untouched.
pub fn encode_model_delta(
    old: &NamedTensors,
    new: &NamedTensors,
    encoding: UpdateEncoding,
) -> Result<Option<(Vec<u8>, NamedTensors)>, CodecError> {
    if encoding == UpdateEncoding::F32 {
        return Ok(None);
    }
    let mut delta = new.zip_map(old, |n, o| n - o)?;
    let payload = match encoding {
        UpdateEncoding::Topk { .. } => {
            let spec = delta.spec();
            let mut out = vec![encoding_tag(encoding)];
            out.extend_from_slice(&(delta.len() as u32).to_le_bytes());
            for ((name, shape), (_, t)) in spec.iter().zip(delta.iter()) {
                write_tensor_header(&mut out, name, shape);
                write_nonzero(&t.values, &mut out);
            }
            out
        }
        _ => encode_delta_payload(&mut delta, encoding),
    };
    let model = apply_model_delta(old, &payload)?;
    Ok(Some((payload, model)))
}

/// `held` plus one delta payload of [`encode_model_delta`], read in its own encoding.
fn apply_model_delta(held: &NamedTensors, payload: &[u8]) -> Result<NamedTensors, CodecError> {
    let tag = *payload.first().ok_or(CodecError::Truncated { needed: 1, got: 0 })?;
    let delta = decode_payload(payload, &held.spec(), model_delta_encoding(tag)?)?;
    Ok(delta.into_model(held)?)
}

/// Bytes of a chain of `steps` model deltas whose payloads take `payload_bytes` together ([`encode_model_deltas`]).
pub fn model_deltas_len(steps: usize, payload_bytes: usize) -> usize {
    16 + 8 * steps + payload_bytes
}

/// The chain of model deltas from version `from` as served: `u64` from, `u64` to (`from` plus the number of
/// payloads), then per payload, in order (the first takes `from` to `from + 1`), its `u64` length and bytes.
pub fn encode_model_deltas<'a>(from: u64, payloads: impl ExactSizeIterator<Item = &'a [u8]>) -> Vec<u8> {
    let to = from + payloads.len() as u64;
    let mut out = Vec::new();
    out.extend_from_slice(&from.to_le_bytes());
    out.extend_from_slice(&to.to_le_bytes());
    for payload in payloads {
        out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        out.extend_from_slice(payload);
    }
    out
}

/// The global model of version `to` from `held`, of version `from`, and the chain of deltas served between them
/// ([`encode_model_deltas`]): each payload read in its own encoding and added in order, as the server made each
/// version. Refuses a chain between other versions, a payload longer than any delta of `held`'s tensors, one that
/// does not decode to a finite delta of exactly those tensors, and bytes after the last payload.
pub fn apply_model_deltas(held: &NamedTensors, from: u64, to: u64, chain: &[u8]) -> Result<NamedTensors, CodecError> {
    let mut r = Reader::new(chain);
    let got = (r.u64()?, r.u64()?);
    if got != (from, to) || to <= from {
        return Err(CodecError::DeltaVersions { expected: (from, to), got });
    }
    // Top-k's layout with every value kept is the longest any delta encoding writes.
    let limit = payload_len(&held.spec(), UpdateEncoding::Topk { fraction: 1.0 }) as u64;
    let mut model = held.clone();
    for _ in from..to {
        let len = r.u64()?;
        if len > limit {
            return Err(CodecError::Oversized { len, limit });
        }
        model = apply_model_delta(&model, r.bytes(len as usize)?)?;
    }
    if r.remaining() != 0 {
        return Err(CodecError::Malformed(format!("{} trailing bytes after the last model delta", r.remaining())));
    }
    Ok(model)
}

/// Splits an encoded payload into frames of at most `max_frame_bytes` (header included), each made as it is taken,
/// so that a sender holds one frame beside the payload, not a second copy of it.
pub fn encode_frames(
    payload: &[u8],
    round: u64,
    max_frame_bytes: usize,
) -> impl ExactSizeIterator<Item = Vec<u8>> + '_ {
    assert!(max_frame_bytes > HEADER_LEN, "frame limit must exceed the {HEADER_LEN}-byte header");
    let chunk = max_frame_bytes - HEADER_LEN;
    let crc32 = crc32fast::hash(payload);
    // An empty payload is one empty frame.
    let chunk_count = payload.len().div_ceil(chunk).max(1);
    (0..chunk_count).map(move |i| {
        let c = &payload[(i * chunk).min(payload.len())..((i + 1) * chunk).min(payload.len())];
        let mut frame = Vec::with_capacity(HEADER_LEN + c.len());
        FrameHeader {
            protocol_version: PROTOCOL_VERSION,
            round,
            chunk_index: i as u32,
            chunk_count: chunk_count as u32,
            payload_len: payload.len() as u64,
            crc32,
            chunk_len: c.len() as u32,
        }
        .write(&mut frame);
        frame.extend_from_slice(c);
        frame
    })
}

/// Encodes tensors straight to frames.
pub fn encode_update(tensors: &NamedTensors, round: u64, max_frame_bytes: usize) -> Vec<Vec<u8>> {
    encode_frames(&encode_payload(tensors), round, max_frame_bytes).collect()
}

/// Limits the receiving side enforces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UpdateLimits {
    pub max_frame_bytes: usize,
    pub max_payload_bytes: u64,
}

impl UpdateLimits {
    /// Limits for updates of `spec` under `encoding`: the longest payload plus `headroom` bytes (so an extra
    /// tensor is reported as unexpected rather than oversized).
    pub fn for_spec(spec: &TensorSpec, encoding: UpdateEncoding, max_frame_bytes: usize, headroom: u64) -> Self {
        Self { max_frame_bytes, max_payload_bytes: payload_len(spec, encoding) as u64 + headroom }
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
        UpdateLimits::for_spec(spec, UpdateEncoding::F32, 100, 64)
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
        assert_eq!(payload_bytes, payload_len(&t.spec(), UpdateEncoding::F32));
        let payload = reassemble(&frames, limits(&t.spec())).unwrap();
        assert_eq!(decode_payload(&payload, &t.spec(), UpdateEncoding::F32).unwrap(), UpdateValues::Model(t));
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
        let err = decode_payload(&encode_payload(&nan), &spec, UpdateEncoding::F32).unwrap_err();
        assert_eq!(err, CodecError::Tensor(TensorError::NonFinite { name: "expert.w".into(), index: 3 }));

        let mut extra = t.clone();
        extra.insert("vision.frozen", vec![1], vec![0.0]).unwrap();
        assert_eq!(
            decode_payload(&encode_payload(&extra), &spec, UpdateEncoding::F32).unwrap_err().code(),
            ErrorCode::UnexpectedTensor
        );

        let mut payload = encode_payload(&t);
        payload.push(0);
        assert_eq!(decode_payload(&payload, &spec, UpdateEncoding::F32).unwrap_err().code(), ErrorCode::MalformedFrame);
        let payload = encode_payload(&t);
        assert!(matches!(
            decode_payload(&payload[..payload.len() - 1], &spec, UpdateEncoding::F32),
            Err(CodecError::Malformed(_))
        ));

        let mut oversized = NamedTensors::new();
        oversized.insert("expert.b", vec![1 << 20], vec![0.0; 1 << 20]).unwrap();
        let err = decode_payload(&encode_payload(&oversized), &spec, UpdateEncoding::F32).unwrap_err();
        assert_eq!(err.code(), ErrorCode::ShapeMismatch);
    }

    #[test]
    fn compressed_deltas_round_trip_and_rebuild_the_model() {
        let global = tensors();
        let trained = global.zip_map(&global, |g, _| g * 1.01 + 0.003).unwrap();
        let spec = global.spec();
        for encoding in
            [UpdateEncoding::F16, UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 0.1 }]
        {
            let mut delta = trained.zip_map(&global, |t, g| t - g).unwrap();
            let exact = delta.clone();
            let payload = encode_delta_payload(&mut delta, encoding);
            assert_eq!(payload.len(), payload_len(&spec, encoding), "{encoding:?}");
            let UpdateValues::Delta(received) = decode_payload(&payload, &spec, encoding).unwrap() else {
                panic!("{encoding:?} payloads hold deltas")
            };
            // What was sent plus what was kept back is the exact delta.
            let rebuilt = received.zip_map(&delta, |s, r| s + r).unwrap();
            for ((_, a), (_, b)) in rebuilt.iter().zip(exact.iter()) {
                for (x, y) in a.values.iter().zip(&b.values) {
                    assert!((x - y).abs() <= 1e-6, "{encoding:?}: {x} against {y}");
                }
            }
            let model = UpdateValues::Delta(received).into_model(&global).unwrap();
            assert_eq!(model.spec(), spec);
            let other = if encoding == UpdateEncoding::Int8 { UpdateEncoding::F16 } else { UpdateEncoding::Int8 };
            let err = decode_payload(&payload, &spec, other).unwrap_err();
            assert!(matches!(err, CodecError::Malformed(m) if m.contains("the run asks for")), "{encoding:?}");
        }
        assert!(payload_len(&spec, UpdateEncoding::Int8) < payload_len(&spec, UpdateEncoding::F16));

        let mut huge = global.clone();
        huge.get_mut("expert.b").unwrap().values[0] = f32::MAX;
        let overflow = UpdateValues::Delta(huge).into_model(&global.zip_map(&global, |_, _| f32::MAX).unwrap());
        assert!(matches!(overflow, Err(TensorError::NonFinite { .. })));
    }

    /// Three rounds of a server that publishes each aggregate as [`encode_model_delta`] makes it: a client holding
    /// any earlier version rebuilds the last one bit for bit from the chain, in fewer bytes than the model, and
    /// each version is within the encoding's bound of its aggregate.
    #[test]
    fn model_deltas_rebuild_the_servers_models_bit_for_bit() {
        let v0 = tensors();
        let model_bytes = v0.to_safetensors().unwrap().len();
        for encoding in
            [UpdateEncoding::F16, UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 0.01 }]
        {
            let mut server = vec![v0.clone()];
            let mut payloads = Vec::new();
            for round in 1..=3u64 {
                let old = server.last().unwrap();
                // An aggregate that moves every fifth value (a top-k run's is sparse), by amounts of many scales.
                let mut aggregate = old.clone();
                for (_, values) in aggregate.iter_mut() {
                    for (i, v) in values.iter_mut().enumerate().filter(|(i, _)| i % 5 == round as usize % 5) {
                        *v += (i as f32 * 0.37 + round as f32).sin() * 10f32.powi(-(i as i32 % 4));
                    }
                }
                let (payload, model) = encode_model_delta(old, &aggregate, encoding).unwrap().unwrap();
                for ((_, m), ((_, a), (_, o))) in model.iter().zip(aggregate.iter().zip(old.iter())) {
                    let largest = a.values.iter().zip(&o.values).fold(0f32, |l, (a, o)| l.max((a - o).abs()));
                    for (m, a) in m.values.iter().zip(&a.values) {
                        assert!((m - a).abs() <= largest / 254.0 * 1.01 + 1e-6, "{encoding:?}: {m} against {a}");
                    }
                }
                assert!(model_deltas_len(1, payload.len()) < model_bytes, "{encoding:?}: {} bytes", payload.len());
                payloads.push(payload);
                server.push(model);
            }
            for from in 0..3 {
                let chain = encode_model_deltas(from, payloads[from as usize..].iter().map(Vec::as_slice));
                let rebuilt = apply_model_deltas(&server[from as usize], from, 3, &chain).unwrap();
                assert_eq!(rebuilt.checksum(), server[3].checksum(), "{encoding:?} from version {from}");
                assert_eq!(rebuilt, server[3]);
            }
        }
        assert!(encode_model_delta(&v0, &v0, UpdateEncoding::F32).unwrap().is_none(), "f32 runs serve models whole");
    }

    #[test]
    fn malformed_or_mismatched_model_deltas_are_refused_with_typed_errors() {
        let v0 = tensors();
        let v1 = v0.zip_map(&v0, |g, _| g + 0.5).unwrap();
        let (payload, model) = encode_model_delta(&v0, &v1, UpdateEncoding::Int8).unwrap().unwrap();
        let chain = encode_model_deltas(0, [payload.as_slice()].into_iter());
        assert_eq!(apply_model_deltas(&v0, 0, 1, &chain).unwrap(), model);
        let apply = |chain: &[u8]| apply_model_deltas(&v0, 0, 1, chain).unwrap_err();

        assert_eq!(
            apply_model_deltas(&v0, 1, 2, &chain).unwrap_err(),
            CodecError::DeltaVersions { expected: (1, 2), got: (0, 1) }
        );
        let backwards = encode_model_deltas(1, std::iter::empty());
        assert!(matches!(apply_model_deltas(&v0, 1, 1, &backwards), Err(CodecError::DeltaVersions { .. })));
        assert!(matches!(apply(&chain[..chain.len() - 1]), CodecError::Truncated { .. }));
        let mut trailing = chain.clone();
        trailing.push(0);
        assert!(matches!(apply(&trailing), CodecError::Malformed(m) if m.contains("trailing")));
        let mut long = chain.clone();
        long[16..24].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(apply(&long), CodecError::Oversized { .. }));
        // An update's f32 payload, and an unknown encoding, are no model delta.
        let f32_chain = encode_model_deltas(0, [encode_payload(&v1).as_slice()].into_iter());
        assert!(matches!(apply(&f32_chain), CodecError::Malformed(m) if m.contains("f32")));
        let mut unknown = payload.clone();
        unknown[0] = 9;
        assert!(matches!(apply(&encode_model_deltas(0, [unknown.as_slice()].into_iter())), CodecError::Malformed(_)));
        // A delta of other tensors than the held ones.
        let mut held = v0.clone();
        held.insert("expert.extra", vec![2], vec![0.0; 2]).unwrap();
        assert_eq!(apply_model_deltas(&held, 0, 1, &chain).unwrap_err().code(), ErrorCode::MissingTensor);
        let mut reshaped = NamedTensors::new();
        reshaped.insert("expert.w", vec![150], v0.get("expert.w").unwrap().values.clone()).unwrap();
        reshaped.insert("expert.b", vec![3], vec![0.0; 3]).unwrap();
        assert_eq!(apply_model_deltas(&reshaped, 0, 1, &chain).unwrap_err().code(), ErrorCode::ShapeMismatch);
        // A change that is not finite is refused where the server makes it, and where a client would apply it.
        let mut nan = v1.clone();
        nan.get_mut("expert.b").unwrap().values[1] = f32::NAN;
        let err = encode_model_delta(&v0, &nan, UpdateEncoding::Topk { fraction: 0.1 }).unwrap_err();
        assert_eq!(err, CodecError::Tensor(TensorError::NonFinite { name: "expert.b".into(), index: 1 }));
        let mut overflow = v0.clone();
        overflow.get_mut("expert.b").unwrap().values[0] = f32::MAX;
        let (big, _) = encode_model_delta(&v0, &overflow, UpdateEncoding::Topk { fraction: 0.1 }).unwrap().unwrap();
        let err = apply_model_deltas(&overflow, 0, 1, &encode_model_deltas(0, [big.as_slice()].into_iter()));
        assert!(matches!(err, Err(CodecError::Tensor(TensorError::NonFinite { .. }))), "{err:?}");
    }
}
