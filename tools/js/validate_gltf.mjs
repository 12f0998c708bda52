// Prints the Khronos glTF validator's JSON report for one .glb / .gltf file: node validate_gltf.mjs FILE
// Exit 0 with the report on stdout whatever it finds (the caller judges it); 2 when the validator cannot run
// (unreadable file, undetectable format). External resources of a .gltf are read from beside it.
import { readFile } from 'node:fs/promises';
import { basename, dirname, resolve } from 'node:path';
import { validateBytes, version } from 'gltf-validator';

const file = process.argv[2];
if (!file || process.argv.length > 3) {
    console.error('usage: node validate_gltf.mjs FILE.glb|FILE.gltf');
    process.exit(2);
}

try {
    const bytes = new Uint8Array(await readFile(file));
    const report = await validateBytes(bytes, {
        uri: basename(file),
        maxIssues: 0,            // every issue, not the first 100
        writeTimestamp: false,
        externalResourceFunction: async (uri) =>
            new Uint8Array(await readFile(resolve(dirname(file), decodeURIComponent(uri)))),
    });
    report.validatorVersion = version();
    process.stdout.write(JSON.stringify(report, null, 1) + '\n');
} catch (error) {
    console.error(`gltf-validator could not validate ${file}: ${error}`);
    process.exit(2);
}
