//! A minimal ISO-BMFF (mp4) muxer and demuxer for one video track: what LeRobot's PyAV reads and writes.
//!
//! Writing streams samples into `mdat` (so a whole camera file never sits in memory) and appends `moov`
//! at the end. Every frame lasts exactly `timescale / fps` ticks, so frame k of the file is presented at
//! k / fps seconds, which is what the per-episode `from_timestamp` in LeRobot's episode table relies on.
//! Reading parses only the sample tables needed to find and fetch samples (stts, ctts, stsz, stsc,
//! stco/co64, stss) and the codec configuration (avcC for H.264, av1C for AV1).

#[cfg(feature = "io")]
use std::fs::File;
#[cfg(feature = "io")]
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::{DataError, Result};
use crate::files::DatasetFiles;

#[cfg(feature = "io")]
/// Ticks per frame; the track timescale is `fps * TICKS_PER_FRAME` so every frame time is exact.
const TICKS_PER_FRAME: u32 = 512;

#[cfg(feature = "io")]
/// H.264 parameter sets that go into the `avcC` box.
pub struct AvcParameterSets {
    pub sps: Vec<u8>,
    pub pps: Vec<u8>,
}

#[cfg(feature = "io")]
/// Streams one H.264 track into an mp4 file.
pub struct Mp4Writer {
    path: PathBuf,
    out: BufWriter<File>,
    width: u16,
    height: u16,
    fps: u32,
    mdat_start: u64,
    next_offset: u64,
    sample_offsets: Vec<u64>,
    sample_sizes: Vec<u32>,
    sync_samples: Vec<u32>,
    parameter_sets: Option<AvcParameterSets>,
}

#[cfg(feature = "io")]
impl Mp4Writer {
    pub fn create(path: &Path, width: u16, height: u16, fps: u32) -> Result<Self> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
        }
        let file = File::create(path).map_err(|e| DataError::io(path, e))?;
        let mut out = BufWriter::new(file);
        let mut head = Vec::new();
        write_box(&mut head, b"ftyp", |b| {
            b.extend_from_slice(b"isom");
            b.extend_from_slice(&0x200u32.to_be_bytes());
            for brand in [b"isom", b"iso2", b"avc1", b"mp41"] {
                b.extend_from_slice(brand);
            }
        });
        let mdat_start = head.len() as u64;
        // mdat with a 64-bit size, patched in `finish` once the payload length is known.
        head.extend_from_slice(&1u32.to_be_bytes());
        head.extend_from_slice(b"mdat");
        head.extend_from_slice(&0u64.to_be_bytes());
        out.write_all(&head).map_err(|e| DataError::io(path, e))?;
        let next_offset = head.len() as u64;
        Ok(Self {
            path: path.to_path_buf(),
            out,
            width,
            height,
            fps,
            mdat_start,
            next_offset,
            sample_offsets: Vec::new(),
            sample_sizes: Vec::new(),
            sync_samples: Vec::new(),
            parameter_sets: None,
        })
    }

    /// Appends one frame (length-prefixed NAL units, 4-byte lengths).
    pub fn push_sample(&mut self, avcc_sample: &[u8], is_sync: bool) -> Result<()> {
        self.out.write_all(avcc_sample).map_err(|e| DataError::io(&self.path, e))?;
        self.sample_offsets.push(self.next_offset);
        self.sample_sizes.push(avcc_sample.len() as u32);
        if is_sync {
            self.sync_samples.push(self.sample_sizes.len() as u32);
        }
        self.next_offset += avcc_sample.len() as u64;
        Ok(())
    }

    /// Records the SPS/PPS for `avcC` (the first ones seen win; the encoder keeps them constant).
    pub fn set_parameter_sets(&mut self, sets: AvcParameterSets) {
        if self.parameter_sets.is_none() {
            self.parameter_sets = Some(sets);
        }
    }

    pub fn frame_count(&self) -> usize {
        self.sample_sizes.len()
    }

    pub fn bytes_written(&self) -> u64 {
        self.next_offset
    }

    pub fn finish(mut self) -> Result<()> {
        let sets = self
            .parameter_sets
            .take()
            .ok_or_else(|| DataError::Encode(format!("{}: no SPS/PPS produced", self.path.display())))?;
        let moov = self.build_moov(&sets);
        let path = self.path.clone();
        let io = |e| DataError::io(&path, e);
        self.out.write_all(&moov).map_err(io)?;
        let mdat_size = self.next_offset - self.mdat_start;
        self.out.seek(SeekFrom::Start(self.mdat_start + 8)).map_err(io)?;
        self.out.write_all(&mdat_size.to_be_bytes()).map_err(io)?;
        self.out.flush().map_err(io)?;
        Ok(())
    }

    fn build_moov(&self, sets: &AvcParameterSets) -> Vec<u8> {
        let timescale = self.fps * TICKS_PER_FRAME;
        let n = self.sample_sizes.len() as u32;
        let media_duration = u64::from(n) * u64::from(TICKS_PER_FRAME);
        let movie_duration_ms = media_duration * 1000 / u64::from(timescale);
        let mut moov = Vec::new();
        write_box(&mut moov, b"moov", |b| {
            write_full_box(b, b"mvhd", 0, 0, |b| {
                put_u32s(b, &[0, 0, 1000, movie_duration_ms as u32, 0x0001_0000]);
                b.extend_from_slice(&0x0100u16.to_be_bytes());
                b.extend_from_slice(&[0; 10]);
                put_u32s(b, &UNITY_MATRIX);
                b.extend_from_slice(&[0; 24]);
                put_u32s(b, &[2]);
            });
            write_box(b, b"trak", |b| {
                write_full_box(b, b"tkhd", 0, 3, |b| {
                    put_u32s(b, &[0, 0, 1, 0, movie_duration_ms as u32, 0, 0]);
                    b.extend_from_slice(&[0; 8]); // layer, alternate group, volume, reserved
                    put_u32s(b, &UNITY_MATRIX);
                    put_u32s(b, &[u32::from(self.width) << 16, u32::from(self.height) << 16]);
                });
                write_box(b, b"mdia", |b| {
                    write_full_box(b, b"mdhd", 0, 0, |b| {
                        put_u32s(b, &[0, 0, timescale, media_duration as u32]);
                        b.extend_from_slice(&0x55c4u16.to_be_bytes()); // "und"
                        b.extend_from_slice(&[0, 0]);
                    });
                    write_full_box(b, b"hdlr", 0, 0, |b| {
                        put_u32s(b, &[0]);
                        b.extend_from_slice(b"vide");
                        b.extend_from_slice(&[0; 12]);
                        b.extend_from_slice(b"VideoHandler\0");
                    });
                    write_box(b, b"minf", |b| {
                        write_full_box(b, b"vmhd", 0, 1, |b| b.extend_from_slice(&[0; 8]));
                        write_box(b, b"dinf", |b| {
                            write_full_box(b, b"dref", 0, 0, |b| {
                                put_u32s(b, &[1]);
                                write_full_box(b, b"url ", 0, 1, |_| {});
                            });
                        });
                        write_box(b, b"stbl", |b| self.write_stbl(b, sets));
                    });
                });
            });
        });
        moov
    }

    fn write_stbl(&self, b: &mut Vec<u8>, sets: &AvcParameterSets) {
        let n = self.sample_sizes.len() as u32;
        write_full_box(b, b"stsd", 0, 0, |b| {
            put_u32s(b, &[1]);
            write_box(b, b"avc1", |b| {
                b.extend_from_slice(&[0; 6]);
                b.extend_from_slice(&1u16.to_be_bytes()); // data reference index
                b.extend_from_slice(&[0; 16]);
                b.extend_from_slice(&self.width.to_be_bytes());
                b.extend_from_slice(&self.height.to_be_bytes());
                put_u32s(b, &[0x0048_0000, 0x0048_0000, 0]);
                b.extend_from_slice(&1u16.to_be_bytes()); // frame count
                b.extend_from_slice(&[0; 32]); // compressor name
                b.extend_from_slice(&0x0018u16.to_be_bytes());
                b.extend_from_slice(&(-1i16).to_be_bytes());
                write_box(b, b"avcC", |b| {
                    let profile = sets.sps.get(1..4).unwrap_or(&[66, 0, 30]);
                    b.push(1);
                    b.extend_from_slice(profile);
                    b.push(0xFF); // 4-byte NAL lengths
                    b.push(0xE1); // one SPS
                    b.extend_from_slice(&(sets.sps.len() as u16).to_be_bytes());
                    b.extend_from_slice(&sets.sps);
                    b.push(1);
                    b.extend_from_slice(&(sets.pps.len() as u16).to_be_bytes());
                    b.extend_from_slice(&sets.pps);
                });
            });
        });
        write_full_box(b, b"stts", 0, 0, |b| put_u32s(b, &[1, n, TICKS_PER_FRAME]));
        write_full_box(b, b"stss", 0, 0, |b| {
            put_u32s(b, &[self.sync_samples.len() as u32]);
            put_u32s(b, &self.sync_samples);
        });
        // One sample per chunk keeps stsc trivial; the offsets table is as long as the sample list either way.
        write_full_box(b, b"stsc", 0, 0, |b| put_u32s(b, &[1, 1, 1, 1]));
        write_full_box(b, b"stsz", 0, 0, |b| {
            put_u32s(b, &[0, n]);
            put_u32s(b, &self.sample_sizes);
        });
        if self.next_offset <= u64::from(u32::MAX) {
            write_full_box(b, b"stco", 0, 0, |b| {
                put_u32s(b, &[n]);
                for &o in &self.sample_offsets {
                    b.extend_from_slice(&(o as u32).to_be_bytes());
                }
            });
        } else {
            write_full_box(b, b"co64", 0, 0, |b| {
                put_u32s(b, &[n]);
                for &o in &self.sample_offsets {
                    b.extend_from_slice(&o.to_be_bytes());
                }
            });
        }
    }
}

#[cfg(feature = "io")]
const UNITY_MATRIX: [u32; 9] = [0x0001_0000, 0, 0, 0, 0x0001_0000, 0, 0, 0, 0x4000_0000];

#[cfg(feature = "io")]
fn put_u32s(b: &mut Vec<u8>, values: &[u32]) {
    for v in values {
        b.extend_from_slice(&v.to_be_bytes());
    }
}

#[cfg(feature = "io")]
fn write_box(out: &mut Vec<u8>, kind: &[u8; 4], body: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(kind);
    body(out);
    let size = (out.len() - start) as u32;
    out[start..start + 4].copy_from_slice(&size.to_be_bytes());
}

#[cfg(feature = "io")]
fn write_full_box(out: &mut Vec<u8>, kind: &[u8; 4], version: u8, flags: u32, body: impl FnOnce(&mut Vec<u8>)) {
    write_box(out, kind, |b| {
        b.extend_from_slice(&((u32::from(version) << 24) | (flags & 0x00FF_FFFF)).to_be_bytes());
        body(b);
    });
}

/// The codec of a video track and its decoder configuration record.
#[derive(Debug, Clone)]
pub enum TrackCodec {
    /// `avcC` contents.
    H264 {
        avcc: Vec<u8>,
    },
    /// `av1C` contents (4 header bytes, then configuration OBUs).
    Av1 {
        av1c: Vec<u8>,
    },
    Other {
        fourcc: String,
    },
}

impl TrackCodec {
    /// The codec string (RFC 6381) a browser's WebCodecs `VideoDecoder` is configured with, e.g. `avc1.42C01E` or
    /// `av01.0.04M.08`; `None` for a codec this crate does not know, or a configuration too short to name it.
    pub fn codec_string(&self) -> Option<String> {
        match self {
            TrackCodec::H264 { avcc } => {
                let profile = avcc.get(1..4)?;
                Some(format!("avc1.{:02X}{:02X}{:02X}", profile[0], profile[1], profile[2]))
            }
            TrackCodec::Av1 { av1c } => {
                let (b1, b2) = (*av1c.get(1)?, *av1c.get(2)?);
                let (profile, level) = (b1 >> 5, b1 & 0x1F);
                let tier = if b2 & 0x80 != 0 { 'H' } else { 'M' };
                let depth = match (b2 & 0x40 != 0, b2 & 0x20 != 0) {
                    (true, true) => 12,
                    (true, false) => 10,
                    _ => 8,
                };
                Some(format!("av01.{profile}.{level:02}{tier}.{depth:02}"))
            }
            TrackCodec::Other { .. } => None,
        }
    }

    /// The decoder configuration record (`avcC` or `av1C` contents): WebCodecs' `description`.
    pub fn configuration(&self) -> &[u8] {
        match self {
            TrackCodec::H264 { avcc } => avcc,
            TrackCodec::Av1 { av1c } => av1c,
            TrackCodec::Other { .. } => &[],
        }
    }
}

/// The sample table of the first video track of an mp4 file.
#[derive(Debug, Clone)]
pub struct Mp4Track {
    /// The file as messages name it.
    pub path: PathBuf,
    /// The file as its dataset's files name it (relative to the root).
    pub file: PathBuf,
    pub codec: TrackCodec,
    pub width: u32,
    pub height: u32,
    pub timescale: u32,
    /// Presentation time of each sample in timescale ticks, in decode order.
    pub pts: Vec<i64>,
    pub offsets: Vec<u64>,
    pub sizes: Vec<u32>,
    /// Per sample: whether decoding can start there.
    pub is_sync: Vec<bool>,
}

impl Mp4Track {
    /// Finds and parses the moov box of video `path` of `files`, reading only box headers and moov itself.
    pub fn open(files: &dyn DatasetFiles, path: &Path) -> Result<Self> {
        let shown = files.display_path(path);
        let len = files.size(path)?;
        let mut pos = 0u64;
        while pos + 8 <= len {
            let header = files.read_range(path, pos, (len - pos).min(16) as usize)?;
            let size32 = u32::from_be_bytes([header[0], header[1], header[2], header[3]]);
            let (size, header_len) = match size32 {
                0 => (len - pos, 8),
                1 => {
                    let wide = header.get(8..16).ok_or_else(|| DataError::mp4(&shown, "truncated box header"))?;
                    let mut b = [0; 8];
                    b.copy_from_slice(wide);
                    (u64::from_be_bytes(b), 16)
                }
                s => (u64::from(s), 8),
            };
            if size < header_len || pos + size > len {
                return Err(DataError::mp4(&shown, "a top-level box runs past the end of the file (truncated?)"));
            }
            if &header[4..8] == b"moov" {
                let moov = files.read_range(path, pos + header_len, (size - header_len) as usize)?;
                return parse_moov(&shown, path, &moov);
            }
            pos += size;
        }
        Err(DataError::mp4(&shown, "no moov box"))
    }

    pub fn sample_time_s(&self, sample: usize) -> f64 {
        self.pts[sample] as f64 / f64::from(self.timescale)
    }

    /// Reads sample `i`'s bytes from `files`.
    pub fn read_sample(&self, files: &dyn DatasetFiles, i: usize) -> Result<Vec<u8>> {
        let (offset, size) = self
            .offsets
            .get(i)
            .zip(self.sizes.get(i))
            .ok_or_else(|| DataError::mp4(&self.path, format!("no sample {i}")))?;
        files
            .read_range(&self.file, *offset, *size as usize)
            .map_err(|_| DataError::mp4(&self.path, format!("sample {i} lies past the end of the file")))
    }
}

struct Reader<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn err(&self, what: &str) -> DataError {
        DataError::mp4(self.path, format!("truncated {what}"))
    }
    fn bytes(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        let s = self.data.get(self.pos..self.pos + n).ok_or_else(|| self.err(what))?;
        self.pos += n;
        Ok(s)
    }
    fn u8(&mut self, what: &str) -> Result<u8> {
        Ok(self.bytes(1, what)?[0])
    }
    fn u16(&mut self, what: &str) -> Result<u16> {
        let b = self.bytes(2, what)?;
        Ok(u16::from_be_bytes([b[0], b[1]]))
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        let b = self.bytes(4, what)?;
        Ok(u32::from_be_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        let b = self.bytes(8, what)?;
        let mut a = [0; 8];
        a.copy_from_slice(b);
        Ok(u64::from_be_bytes(a))
    }
}

/// Splits `data` into (fourcc, body) boxes.
fn boxes<'a>(path: &Path, data: &'a [u8]) -> Result<Vec<([u8; 4], &'a [u8])>> {
    let mut out = Vec::new();
    let mut r = Reader { path, data, pos: 0 };
    while r.pos + 8 <= data.len() {
        let start = r.pos;
        let size32 = r.u32("box header")?;
        let mut kind = [0; 4];
        kind.copy_from_slice(r.bytes(4, "box header")?);
        let size = match size32 {
            0 => (data.len() - start) as u64,
            1 => r.u64("box header")?,
            s => u64::from(s),
        };
        let header = r.pos - start;
        let end = start.checked_add(size as usize).filter(|&e| e <= data.len() && size as usize >= header);
        let end = end.ok_or_else(|| {
            DataError::mp4(path, format!("box {} runs past the end of the file", String::from_utf8_lossy(&kind)))
        })?;
        out.push((kind, &data[r.pos..end]));
        r.pos = end;
    }
    Ok(out)
}

fn child<'a>(path: &Path, parent: &'a [u8], kind: &[u8; 4]) -> Result<&'a [u8]> {
    boxes(path, parent)?
        .into_iter()
        .find(|(k, _)| k == kind)
        .map(|(_, b)| b)
        .ok_or_else(|| DataError::mp4(path, format!("no {} box", String::from_utf8_lossy(kind))))
}

fn optional_child<'a>(path: &Path, parent: &'a [u8], kind: &[u8; 4]) -> Result<Option<&'a [u8]>> {
    Ok(boxes(path, parent)?.into_iter().find(|(k, _)| k == kind).map(|(_, b)| b))
}

fn parse_moov(path: &Path, file: &Path, moov: &[u8]) -> Result<Mp4Track> {
    for (kind, trak) in boxes(path, moov)? {
        if &kind != b"trak" {
            continue;
        }
        let mdia = child(path, trak, b"mdia")?;
        let hdlr = child(path, mdia, b"hdlr")?;
        if hdlr.get(8..12) != Some(b"vide") {
            continue;
        }
        return parse_video_trak(path, file, mdia);
    }
    Err(DataError::mp4(path, "no video track"))
}

fn parse_video_trak(path: &Path, file: &Path, mdia: &[u8]) -> Result<Mp4Track> {
    let mdhd = child(path, mdia, b"mdhd")?;
    let mut r = Reader { path, data: mdhd, pos: 0 };
    let version = r.u8("mdhd")?;
    r.bytes(3, "mdhd")?;
    let timescale = if version == 1 {
        r.bytes(16, "mdhd")?;
        r.u32("mdhd")?
    } else {
        r.bytes(8, "mdhd")?;
        r.u32("mdhd")?
    };
    if timescale == 0 {
        return Err(DataError::mp4(path, "track timescale is 0"));
    }
    let stbl = child(path, child(path, mdia, b"minf")?, b"stbl")?;

    // stsd: first sample entry.
    let stsd = child(path, stbl, b"stsd")?;
    let entries = boxes(path, stsd.get(8..).ok_or_else(|| DataError::mp4(path, "truncated stsd"))?)?;
    let (fourcc, entry) = entries.first().ok_or_else(|| DataError::mp4(path, "empty stsd"))?;
    // VisualSampleEntry: 6 reserved + 2 dref index + 16 pre-defined, then width/height, then 50 more bytes.
    let mut r = Reader { path, data: entry, pos: 24 };
    let width = u32::from(r.u16("sample entry")?);
    let height = u32::from(r.u16("sample entry")?);
    let config_boxes = entry.get(78..).ok_or_else(|| DataError::mp4(path, "truncated sample entry"))?;
    let codec = match fourcc {
        b"avc1" | b"avc3" => TrackCodec::H264 { avcc: child(path, config_boxes, b"avcC")?.to_vec() },
        b"av01" => TrackCodec::Av1 { av1c: child(path, config_boxes, b"av1C")?.to_vec() },
        other => TrackCodec::Other { fourcc: String::from_utf8_lossy(other).into_owned() },
    };

    // Decode times from stts, composition offsets from ctts.
    let mut dts = Vec::new();
    let stts = child(path, stbl, b"stts")?;
    let mut r = Reader { path, data: stts, pos: 4 };
    let mut t: i64 = 0;
    for _ in 0..r.u32("stts")? {
        let count = r.u32("stts")?;
        let delta = r.u32("stts")?;
        for _ in 0..count {
            dts.push(t);
            t += i64::from(delta);
        }
    }
    let mut pts = dts;
    if let Some(ctts) = optional_child(path, stbl, b"ctts")? {
        let mut r = Reader { path, data: ctts, pos: 0 };
        let version = r.u8("ctts")?;
        r.bytes(3, "ctts")?;
        let mut i = 0;
        for _ in 0..r.u32("ctts")? {
            let count = r.u32("ctts")?;
            let raw = r.u32("ctts")?;
            let offset = if version == 1 { i64::from(raw as i32) } else { i64::from(raw) };
            for _ in 0..count {
                if let Some(p) = pts.get_mut(i) {
                    *p += offset;
                }
                i += 1;
            }
        }
    }

    let stsz = child(path, stbl, b"stsz")?;
    let mut r = Reader { path, data: stsz, pos: 4 };
    let uniform = r.u32("stsz")?;
    let n = r.u32("stsz")? as usize;
    let sizes =
        if uniform != 0 { vec![uniform; n] } else { (0..n).map(|_| r.u32("stsz")).collect::<Result<Vec<_>>>()? };

    let chunk_offsets: Vec<u64> = if let Some(stco) = optional_child(path, stbl, b"stco")? {
        let mut r = Reader { path, data: stco, pos: 4 };
        let c = r.u32("stco")?;
        (0..c).map(|_| r.u32("stco").map(u64::from)).collect::<Result<_>>()?
    } else {
        let co64 = child(path, stbl, b"co64")?;
        let mut r = Reader { path, data: co64, pos: 4 };
        let c = r.u32("co64")?;
        (0..c).map(|_| r.u64("co64")).collect::<Result<_>>()?
    };
    let stsc = child(path, stbl, b"stsc")?;
    let mut r = Reader { path, data: stsc, pos: 4 };
    let runs: Vec<(u32, u32)> = (0..r.u32("stsc")?)
        .map(|_| -> Result<(u32, u32)> {
            let first = r.u32("stsc")?;
            let per_chunk = r.u32("stsc")?;
            r.u32("stsc")?;
            Ok((first, per_chunk))
        })
        .collect::<Result<_>>()?;
    let mut offsets = Vec::with_capacity(n);
    for (ri, &(first, per_chunk)) in runs.iter().enumerate() {
        let last = runs.get(ri + 1).map_or(chunk_offsets.len() as u32 + 1, |r| r.0);
        for chunk in first..last {
            let mut off = *chunk_offsets
                .get(chunk as usize - 1)
                .ok_or_else(|| DataError::mp4(path, "stsc names a chunk that stco lacks"))?;
            for _ in 0..per_chunk {
                if offsets.len() == n {
                    break;
                }
                offsets.push(off);
                off += u64::from(sizes[offsets.len() - 1]);
            }
        }
    }
    if offsets.len() != n || pts.len() != n {
        return Err(DataError::mp4(
            path,
            format!("sample tables disagree: {n} sizes, {} offsets, {} times", offsets.len(), pts.len()),
        ));
    }
    let is_sync = match optional_child(path, stbl, b"stss")? {
        None => vec![true; n],
        Some(stss) => {
            let mut flags = vec![false; n];
            let mut r = Reader { path, data: stss, pos: 4 };
            for _ in 0..r.u32("stss")? {
                let s = r.u32("stss")? as usize;
                if let Some(f) = s.checked_sub(1).and_then(|i| flags.get_mut(i)) {
                    *f = true;
                }
            }
            flags
        }
    };
    Ok(Mp4Track {
        path: path.to_path_buf(),
        file: file.to_path_buf(),
        codec,
        width,
        height,
        timescale,
        pts,
        offsets,
        sizes,
        is_sync,
    })
}
