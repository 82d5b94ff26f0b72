// The Khronos glTF validator (npm gltf-validator) on one .glb or .gltf: prints its report's issues as JSON.
// Usage: node gltf_validate.mjs NODE_MODULES FILE
import fs from 'fs';
import path from 'path';
import { createRequire } from 'module';

const [modules, file] = process.argv.slice(2);
const validator = createRequire(path.join(modules, 'index.js'))('gltf-validator');
const external = async (uri) => new Uint8Array(fs.readFileSync(path.join(path.dirname(file), decodeURIComponent(uri))));
const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)),
	{ uri: file, maxIssues: 1000, externalResourceFunction: external });
console.log(JSON.stringify(report.issues));
