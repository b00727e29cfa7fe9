// What the page reads from a height map's bytes before the upload: the header probe (format,
// size, bit depth, colour, float, GeoTIFF tags of a PNG, TIFF or OpenEXR), the media type to send
// it with, and the range of a PNG's heights. Pure functions of bytes, with no DOM or network
// access, so node can test them on real files. A TIFF's directory may sit anywhere in the file,
// so `probe` takes either the bytes or a `read(offset, length)` function answering an
// ArrayBuffer (app.js reads slices of the dropped File on demand instead of the whole file).

const PNG_COLORS = { 0: 'gray', 2: 'rgb', 3: 'palette', 4: 'gray+alpha', 6: 'rgba' };

/** The media type to send the bytes with, from their magic number ('' when unknown). */
export function sniffType(bytes) {
  const b = bytes;
  if (b.length >= 8 && b[0] === 0x89 && b[1] === 0x50 && b[2] === 0x4e && b[3] === 0x47) {
    return 'image/png';
  }
  if (b.length >= 4 && ((b[0] === 0x49 && b[1] === 0x49 && b[2] === 0x2a && b[3] === 0) ||
      (b[0] === 0x4d && b[1] === 0x4d && b[2] === 0 && b[3] === 0x2a))) {
    return 'image/tiff';
  }
  if (b.length >= 4 && b[0] === 0x76 && b[1] === 0x2f && b[2] === 0x31 && b[3] === 0x01) {
    return 'image/x-exr';
  }
  return '';
}

function png(dv) {
  if (dv.byteLength < 29) throw new Error('truncated PNG header');
  const tag = String.fromCharCode(dv.getUint8(12), dv.getUint8(13), dv.getUint8(14), dv.getUint8(15));
  if (tag !== 'IHDR') throw new Error('PNG without IHDR');
  return {
    format: 'png',
    width: dv.getUint32(16),
    height: dv.getUint32(20),
    bitDepth: dv.getUint8(24),
    color: PNG_COLORS[dv.getUint8(25)] || `type ${dv.getUint8(25)}`,
    float: false,
  };
}

async function tiff(read, dv) {
  const le = dv.getUint8(0) === 0x49;
  const u16 = (v, o) => v.getUint16(o, le);
  const u32 = (v, o) => v.getUint32(o, le);
  const ifdOffset = u32(dv, 4);
  // The IFD may sit anywhere in the file: read it (and the values it points to) on demand.
  const view = async (off, len) => new DataView(await read(off, len));
  const head = await view(ifdOffset, 2);
  if (head.byteLength < 2) throw new Error('truncated TIFF');
  const n = u16(head, 0);
  const ifd = await view(ifdOffset + 2, n * 12);
  if (ifd.byteLength < n * 12) throw new Error('truncated TIFF directory');
  const info = { format: 'tiff', width: 0, height: 0, bitDepth: 0, color: 'gray', float: false };
  let spp = 1;
  for (let i = 0; i < n; i++) {
    const o = i * 12;
    const tag = u16(ifd, o);
    const type = u16(ifd, o + 2);
    const value = type === 3 ? u16(ifd, o + 8) : u32(ifd, o + 8);
    if (tag === 256) info.width = value;
    else if (tag === 257) info.height = value;
    else if (tag === 258) {
      // Inline when the SHORTs fit in 4 bytes, else at an offset: the first sample's depth.
      if (u32(ifd, o + 4) <= 2) info.bitDepth = u16(ifd, o + 8);
      else {
        const at = await view(u32(ifd, o + 8), 2);
        if (at.byteLength === 2) info.bitDepth = u16(at, 0);
      }
    } else if (tag === 277) spp = value;
    else if (tag === 339) info.float = value === 3;
    else if (tag === 34735) info.geoKeys = true; // GeoKeyDirectory: a GeoTIFF (SPEC §2)
    else if (tag === 33550 && type === 12 && u32(ifd, o + 4) >= 2) {
      // ModelPixelScale: DOUBLEs at an offset; the first is the cell width in map units.
      const at = await view(u32(ifd, o + 8), 8);
      if (at.byteLength === 8) info.pixelScale = at.getFloat64(0, le);
    }
  }
  info.color = { 1: 'gray', 2: 'gray+alpha', 3: 'rgb', 4: 'rgba' }[spp] || `${spp} samples`;
  return info;
}

function exr(dv) {
  let o = 8;
  const str = () => {
    let s = '';
    while (o < dv.byteLength) {
      const c = dv.getUint8(o++);
      if (c === 0) return s;
      s += String.fromCharCode(c);
    }
    throw new Error('truncated EXR header');
  };
  const info = { format: 'exr', width: 0, height: 0, bitDepth: 0, color: '', float: true };
  for (;;) {
    const name = str();
    if (name === '') break;
    const type = str();
    const size = dv.getInt32(o, true);
    o += 4;
    if (name === 'dataWindow' && type === 'box2i') {
      const [x0, y0, x1, y1] = [0, 4, 8, 12].map((k) => dv.getInt32(o + k, true));
      info.width = x1 - x0 + 1;
      info.height = y1 - y0 + 1;
    } else if (name === 'channels' && type === 'chlist') {
      let p = o;
      const names = [];
      let bits = 0;
      while (p < o + size) {
        let s = '';
        while (dv.getUint8(p) !== 0) s += String.fromCharCode(dv.getUint8(p++));
        p++;
        if (s === '') break;
        const pt = dv.getInt32(p, true);
        bits = Math.max(bits, pt === 1 ? 16 : 32);
        names.push(s);
        p += 16;
      }
      info.color = names.join(',');
      info.bitDepth = bits;
    }
    o += size;
  }
  return info;
}

/** The bytes of `bytes` (ArrayBuffer, typed array or DataView) as a `read(offset, length)`. */
function readerOf(bytes) {
  const all = ArrayBuffer.isView(bytes)
    ? new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength) : new Uint8Array(bytes);
  // Clamped to the end as Blob.slice is: a read past the end answers fewer bytes.
  return (off, len) => all.slice(off, off + len).buffer;
}

/**
 * The header of a file: {format, width, height, bitDepth, color, float, type}, and for a
 * GeoTIFF `geoKeys` (and `pixelScale` when it has one). `source` is the file's bytes (or its
 * start: a TIFF's directory must be in them), or `read(offset, length)` answering (a promise of)
 * an ArrayBuffer of at most `length` bytes from `offset`, fewer at the end of the file.
 * Throws an Error with a readable message when the bytes are none of PNG, TIFF, OpenEXR.
 */
export async function probe(source) {
  const read = typeof source === 'function' ? source : readerOf(source);
  const head = new Uint8Array(await read(0, 65536));
  const type = sniffType(head);
  const dv = new DataView(head.buffer, head.byteOffset, head.byteLength);
  let info;
  if (type === 'image/png') info = png(dv);
  else if (type === 'image/tiff') info = await tiff(read, dv);
  else if (type === 'image/x-exr') info = exr(dv);
  else throw new Error('not a PNG, TIFF or OpenEXR file');
  return { ...info, type };
}

// ---------------------------------------------------------------------------------------------
// The range of a PNG's heights, before the upload: with the height scale it gives the relief in
// texels (a 16-bit map spanning 236–1076 of 65535 is 0.1 texel at the default scale: a flat
// grey bake). The IDAT stream is inflated with the browser's DecompressionStream and unfiltered
// here, so 16-bit samples keep their precision (an <img> would give 8 bits).

const PNG_CHANNELS = { 0: 1, 2: 3, 4: 2, 6: 4 };
/** Largest map measured in the page (texels); larger ones are measured by the bake. */
const RELIEF_MAX_TEXELS = 4096 * 4096;

/**
 * {min, max} of the normalised samples of the PNG `data` (the whole file: ArrayBuffer or typed
 * array) as the bake reads them with `channel` (luma = 0.2126 R + 0.7152 G + 0.0722 B), or null
 * when it cannot tell (palette, interlaced, under 8 bits, too large, no DecompressionStream).
 */
export async function pngRange(data, channel) {
  const bytes = ArrayBuffer.isView(data)
    ? new Uint8Array(data.buffer, data.byteOffset, data.byteLength) : new Uint8Array(data);
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const w = dv.getUint32(16);
  const h = dv.getUint32(20);
  const depth = bytes[24];
  const ctype = bytes[25];
  const nch = PNG_CHANNELS[ctype];
  if (!nch || bytes[28] !== 0 || (depth !== 8 && depth !== 16) || w * h > RELIEF_MAX_TEXELS) return null;
  if (typeof DecompressionStream === 'undefined') return null;
  const idat = [];
  for (let o = 8; o + 8 <= bytes.length;) {
    const len = dv.getUint32(o);
    const tag = String.fromCharCode(bytes[o + 4], bytes[o + 5], bytes[o + 6], bytes[o + 7]);
    if (tag === 'IDAT') idat.push(bytes.subarray(o + 8, o + 8 + len));
    if (tag === 'IEND') break;
    o += 12 + len;
  }
  const inflated = new Uint8Array(await new Response(
    new Blob(idat).stream().pipeThrough(new DecompressionStream('deflate'))).arrayBuffer());
  const bpp = nch * (depth / 8);
  const stride = w * bpp;
  if (inflated.length < h * (stride + 1)) return null;
  let prev = new Uint8Array(stride);
  let row = new Uint8Array(stride);
  const max = depth === 16 ? 65535 : 255;
  const pick = { r: 0, g: 1, b: 2, a: nch - 1 }[channel];
  let lo = Infinity;
  let hi = -Infinity;
  for (let y = 0; y < h; y++) {
    const at = y * (stride + 1);
    const f = inflated[at];
    const src = inflated.subarray(at + 1, at + 1 + stride);
    for (let i = 0; i < stride; i++) {
      const a = i >= bpp ? row[i - bpp] : 0;
      const b = prev[i];
      const c = i >= bpp ? prev[i - bpp] : 0;
      let v = src[i];
      if (f === 1) v += a;
      else if (f === 2) v += b;
      else if (f === 3) v += (a + b) >> 1;
      else if (f === 4) {
        const p = a + b - c;
        const pa = Math.abs(p - a);
        const pb = Math.abs(p - b);
        const pc = Math.abs(p - c);
        v += pa <= pb && pa <= pc ? a : pb <= pc ? b : c;
      }
      row[i] = v & 255;
    }
    for (let x = 0; x < w; x++) {
      const s = (k) => (depth === 16 ? (row[x * bpp + 2 * k] << 8) | row[x * bpp + 2 * k + 1] : row[x * bpp + k]);
      let v;
      if (nch <= 2) v = channel === 'a' && nch === 2 ? s(1) : s(0);
      else if (pick === undefined) v = 0.2126 * s(0) + 0.7152 * s(1) + 0.0722 * s(2);
      else v = s(Math.min(pick, nch - 1));
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    [prev, row] = [row, prev];
  }
  return { min: lo / max, max: hi / max };
}
