// Builds dist/: the page, React 17's browser builds and Studio's prebuilt bundle, patched.
//
// No bundler: @foxglove/studio-base ships a webpack UMD bundle that takes React and ReactDOM from
// globals (`self.react`, `self["react-dom"]`) and loads its chunks and workers relative to its own
// script's URL, so copying it next to the page is enough.
//
// The one patch: Studio 1.48 offers the WebSocket subprotocol `foxglove.websocket.v1`; the
// foxglove-sdk server (dbml's live view) accepts only `foxglove.sdk.v1`, the same protocol under
// its current name. The build fails if the bundle does not contain the line it patches, so a
// different bundle cannot slip through unpatched.
import { cpSync, mkdirSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const modules = join(here, "node_modules");
const dist = join(here, "dist");

const OLD_PROTOCOL = 'FoxgloveClient.SUPPORTED_SUBPROTOCOL = "foxglove.websocket.v1";';
const NEW_PROTOCOL = 'FoxgloveClient.SUPPORTED_SUBPROTOCOL = "foxglove.sdk.v1";';

rmSync(dist, { recursive: true, force: true });
mkdirSync(join(dist, "vendor"), { recursive: true });

cpSync(join(modules, "@foxglove", "studio-base", "assets"), join(dist, "studio"), {
  recursive: true,
});
const bundlePath = join(dist, "studio", "index.js");
const bundle = readFileSync(bundlePath, "utf8");
const found = bundle.split(OLD_PROTOCOL).length - 1;
if (found !== 1) {
  throw new Error(`expected the client's subprotocol line once in ${bundlePath}, found it ${found} times`);
}
writeFileSync(bundlePath, bundle.replace(OLD_PROTOCOL, NEW_PROTOCOL));

cpSync(join(modules, "react", "umd", "react.production.min.js"), join(dist, "vendor", "react.js"));
cpSync(
  join(modules, "react-dom", "umd", "react-dom.production.min.js"),
  join(dist, "vendor", "react-dom.js"),
);
for (const name of ["index.html", "page.js"]) {
  cpSync(join(here, name), join(dist, name));
}
console.log(`built ${dist}`);
