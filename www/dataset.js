// The volunteer's own LeRobot dataset folder on the join page: picking it (the File System Access API's directory
// picker where the browser has it, an <input webkitdirectory> otherwise), listing it without reading it, reading one
// file only when the wasm volunteer asks (it asks only for what the policy needs), and decoding video samples with
// the browser's WebCodecs VideoDecoder into RGBA pictures. Nothing here sends anything anywhere.

// A folder as the wasm volunteer takes it: its name, every file's path relative to it and size, `read(path)` and
// `decode(request)`. `open(path)` gives the File of a listed path (only then, for FSA handles, is it looked up).
function folder(name, entries) {
  const byPath = new Map(entries.map((e) => [e.path, e.open]));
  return {
    name,
    paths: entries.map((e) => e.path),
    sizes: entries.map((e) => e.size),
    async read(path) {
      const open = byPath.get(path);
      if (!open) throw new Error(`${name}/${path} is not in the picked folder`);
      return new Uint8Array(await (await open()).arrayBuffer());
    },
    decode: decodeSamples,
  };
}

// The folder an <input webkitdirectory> was given: its files' paths start with the folder's name.
export function folderFromInput(fileList) {
  const files = [...fileList];
  if (files.length === 0) return null;
  const name = files[0].webkitRelativePath.split("/")[0];
  const entries = files.map((file) => ({
    path: file.webkitRelativePath.slice(name.length + 1),
    size: file.size,
    open: async () => file,
  }));
  return folder(name, entries);
}

// The folder chosen in the File System Access API's directory picker, listed recursively (names and sizes only).
export async function pickFolder() {
  const root = await window.showDirectoryPicker({ mode: "read" });
  const entries = [];
  async function walk(dir, prefix) {
    for await (const [name, handle] of dir.entries()) {
      if (handle.kind === "directory") {
        await walk(handle, prefix + name + "/");
      } else {
        const size = (await handle.getFile()).size;
        entries.push({ path: prefix + name, size, open: () => handle.getFile() });
      }
    }
  }
  await walk(root, "");
  return folder(root.name, entries);
}

// Decodes one run of video samples (decode order, from a key frame) with WebCodecs: `request` holds the codec
// string, the decoder configuration record (avcC/av1C), the coded size, the first sample's index and the samples
// with their key-frame flags. Each chunk carries its sample index as its timestamp, so every picture says which
// sample it is. Resolves with [{timestamp, width, height, rgba}].
async function decodeSamples(request) {
  const config = {
    codec: request.codec,
    description: request.description,
    codedWidth: request.width,
    codedHeight: request.height,
  };
  const support = await VideoDecoder.isConfigSupported(config);
  if (!support.supported) throw new Error(`this browser's WebCodecs cannot decode ${request.codec} video`);
  const canvas = new OffscreenCanvas(request.width, request.height);
  const context = canvas.getContext("2d", { willReadFrequently: true });
  const pictures = [];
  let failure = null;
  const decoder = new VideoDecoder({
    output: (frame) => {
      try {
        const [width, height] = [frame.displayWidth, frame.displayHeight];
        canvas.width = width;
        canvas.height = height;
        context.drawImage(frame, 0, 0);
        pictures.push({ timestamp: frame.timestamp, width, height, rgba: context.getImageData(0, 0, width, height).data });
      } finally {
        frame.close();
      }
    },
    error: (e) => { failure = e; },
  });
  decoder.configure(config);
  request.samples.forEach((data, i) => {
    decoder.decode(new EncodedVideoChunk({ type: request.keys[i] ? "key" : "delta", timestamp: request.first + i, data }));
  });
  await decoder.flush();
  decoder.close();
  if (failure) throw failure;
  return pictures;
}
