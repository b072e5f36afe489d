// Build the dashboard into dist/: one bundled, minified script (three.js included, nothing
// loaded from a CDN at run time), the page and its stylesheet.
import { copyFile, mkdir, rm } from "node:fs/promises";
import { build } from "esbuild";

const out = "dist";
await rm(out, { recursive: true, force: true });
await mkdir(out, { recursive: true });
await build({
  entryPoints: ["src/main.js"],
  bundle: true,
  minify: true,
  format: "esm",
  target: "es2022",
  outfile: `${out}/app.js`,
  logLevel: "warning",
});
await Promise.all(["index.html", "style.css"].map((file) => copyFile(file, `${out}/${file}`)));
console.log(`dashboard built into ${out}/`);
