// three.js's own KHR_gaussian_splatting loader (GLTFLoader + GLTFGaussianSplatLoaderExtension) on one .glb or
// .gltf, in Node (no renderer is needed to load): prints, as JSON, what it decoded for its GaussianSplat object:
// centres, covariances (xx, xy, xz, yy, yz, zz), colour bytes (RGBA) and the packed SH bytes of each degree.
// Usage: node three_gltf_splats.mjs NODE_MODULES FILE
import fs from 'fs';
import path from 'path';
import { pathToFileURL } from 'url';

const [modules, file] = process.argv.slice(2);
const addon = (name) => import(pathToFileURL(path.join(modules, 'three', 'examples', 'jsm', 'loaders', name)).href);
const { GLTFLoader } = await addon('GLTFLoader.js');
const { GLTFGaussianSplatLoaderExtension } = await addon('GLTFGaussianSplatLoaderExtension.js');

const loader = new GLTFLoader();
loader.register((parser) => new GLTFGaussianSplatLoaderExtension(parser));
// The loader fetches a .gltf's buffer by URL: answer that fetch with the .bin beside the file.
const bytes = fs.readFileSync(file);
const data = path.extname(file) === '.gltf' ? bytes.toString('utf8')
	: bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
if (path.extname(file) === '.gltf') {
	const realFetch = globalThis.fetch;
	globalThis.ProgressEvent ??= class extends Event {  // the loader reports progress with it; Node lacks it
		constructor(type, init) { super(type); Object.assign(this, init); }
	};
	globalThis.fetch = async (url, options) => {
		const href = url instanceof Request ? url.url : String(url);
		const name = decodeURIComponent(href.split('/').pop());
		const local = path.join(path.dirname(file), name);
		return fs.existsSync(local) ? new Response(fs.readFileSync(local)) : realFetch(url, options);
	};
}
const gltf = await loader.parseAsync(data, 'http://splats.invalid/');
const splats = [];
gltf.scene.traverse((object) => { if (object.isGaussianSplat) splats.push(object); });
if (splats.length !== 1) throw new Error(`expected one GaussianSplat, found ${splats.length}`);
const geometry = splats[0].splatGeometry;
const out = { extension: splats[0].userData.gltfExtensions };
for (const [name, attribute] of Object.entries(geometry.attributes)) {
	const array = attribute.array instanceof Uint32Array ? new Uint8Array(attribute.array.buffer) : attribute.array;
	out[name] = { itemSize: attribute.itemSize, count: attribute.count, values: Array.from(array) };
}
console.log(JSON.stringify(out));
