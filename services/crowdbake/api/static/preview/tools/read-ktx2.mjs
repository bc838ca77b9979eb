// Read KTX2 files with ktx-parse (the parser three.js's KTX2Loader uses) and print what it sees:
// header fields, the data format descriptor, key/values, the sha256 of each level's bytes, and whether
// ktx-parse's own writer serialises what it read back to the very same bytes (a layout check).
// Usage: node tools/read-ktx2.mjs FILE.ktx2 [...]
import { createHash } from 'node:crypto';
import { readFileSync } from 'node:fs';
import { read, write } from 'ktx-parse';

const out = [];
for (const path of process.argv.slice(2)) {
  const bytes = new Uint8Array(readFileSync(path));
  const container = read(bytes);
  const again = write(container, { keepWriter: true });
  const dfd = container.dataFormatDescriptor[0];
  out.push({
    path,
    vkFormat: container.vkFormat,
    typeSize: container.typeSize,
    pixelWidth: container.pixelWidth,
    pixelHeight: container.pixelHeight,
    pixelDepth: container.pixelDepth,
    layerCount: container.layerCount,
    faceCount: container.faceCount,
    levelCount: container.levels.length,
    supercompressionScheme: container.supercompressionScheme,
    dfd: {
      colorModel: dfd.colorModel,
      transferFunction: dfd.transferFunction,
      bytesPlane: dfd.bytesPlane,
      samples: dfd.samples.map((s) => ({ bitOffset: s.bitOffset, bitLength: s.bitLength, channelType: s.channelType, sampleUpper: s.sampleUpper })),
    },
    keyValue: Object.fromEntries(Object.entries(container.keyValue).map(([k, v]) => [k, typeof v === 'string' ? v : Buffer.from(v).toString()])),
    reserialisedIdentical: again.length === bytes.length && again.every((value, i) => value === bytes[i]),
    levels: container.levels.map((level) => ({
      bytes: level.levelData.byteLength,
      sha256: createHash('sha256').update(level.levelData).digest('hex'),
    })),
  });
}
console.log(JSON.stringify(out, null, 2));
