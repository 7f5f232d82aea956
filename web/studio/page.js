// Renders Foxglove Studio's App with settings kept in memory and one preset layout.
//
// The layout is fetched at run time from the `layout` query parameter (default: layout.json next
// to this page), so the page never needs rebuilding when dbml's layout changes. The data source
// comes from the usual deep-link parameters, which Studio reads itself:
//   ?ds=foxglove-websocket&ds.url=ws://127.0.0.1:8765
//   ?ds=remote-file&ds.url=http://127.0.0.1:8000/run.mcap
// window.dbmlStudio.state tells a driver how far the page got: "loading", "rendered" or "error"
// (then window.dbmlStudio.error says why).
"use strict";

const LAYOUT_ID = "dbml";

// Nothing that would reach the internet or ask the user first: no telemetry, no crash reports,
// no update checks, no sign-in prompt, no "open a file" dialog, no "web or desktop?" screen.
const SETTINGS = {
  colorScheme: "dark",
  language: "en",
  launchPreference: "web",
  "telemetry.telemetryEnabled": false,
  "telemetry.crashReportingEnabled": false,
  "updates.enabled": false,
  hideSignInPrompt: true,
  "ui.open-dialog-startup": false,
};

class MemoryAppConfiguration {
  constructor(values) {
    this.values = new Map(Object.entries(values));
    this.listeners = new Map();
  }
  get(key) {
    return this.values.get(key);
  }
  async set(key, value) {
    this.values.set(key, value);
    for (const listener of [...(this.listeners.get(key) ?? [])]) {
      listener(value);
    }
  }
  addChangeListener(key, listener) {
    if (!this.listeners.has(key)) {
      this.listeners.set(key, new Set());
    }
    this.listeners.get(key).add(listener);
  }
  removeChangeListener(key, listener) {
    this.listeners.get(key)?.delete(listener);
  }
}

// Every namespace Studio asks for starts with the preset layout; edits stay in memory.
class MemoryLayoutStorage {
  constructor(preset) {
    this.preset = preset;
    this.byNamespace = new Map();
  }
  namespace(name) {
    if (!this.byNamespace.has(name)) {
      this.byNamespace.set(name, new Map([[this.preset.id, this.preset]]));
    }
    return this.byNamespace.get(name);
  }
  async list(namespace) {
    return [...this.namespace(namespace).values()];
  }
  async get(namespace, id) {
    return this.namespace(namespace).get(id);
  }
  async put(namespace, layout) {
    this.namespace(namespace).set(layout.id, layout);
    return layout;
  }
  async delete(namespace, id) {
    this.namespace(namespace).delete(id);
  }
  async importLayouts() {}
}

async function main() {
  window.dbmlStudio = { state: "loading", error: undefined };
  const layoutUrl = new URLSearchParams(window.location.search).get("layout") ?? "layout.json";
  const response = await fetch(layoutUrl, { cache: "no-store" });
  if (!response.ok) {
    throw new Error(`layout ${layoutUrl}: HTTP ${response.status}`);
  }
  const data = await response.json();
  const preset = {
    id: LAYOUT_ID,
    name: "dbml",
    permission: "CREATOR_WRITE",
    baseline: { data, savedAt: new Date().toISOString() },
    working: undefined,
    syncInfo: undefined,
  };
  // Studio opens the layout its user profile names.
  window.localStorage.setItem("studio.profile-data", JSON.stringify({ currentLayoutId: LAYOUT_ID }));
  window.localStorage.setItem("i18nextLng", "en");
  // The panels get the whole width: the data source's sidebar starts closed (its icon opens it).
  window.localStorage.setItem(
    "fox.workspace",
    JSON.stringify({ state: { sidebarItem: null }, version: 0 }),
  );

  await window.initI18n();
  const app = window.React.createElement(window.App, {
    deepLinks: [window.location.href],
    appConfiguration: new MemoryAppConfiguration(SETTINGS),
    dataSources: [
      new window.FoxgloveWebSocketDataSourceFactory(),
      new window.RemoteDataSourceFactory(),
    ],
    layoutStorage: new MemoryLayoutStorage(preset),
    extensionLoaders: [],
    enableGlobalCss: true,
  });
  window.ReactDOM.render(app, document.getElementById("root"));
  window.dbmlStudio.state = "rendered";
}

main().catch((error) => {
  window.dbmlStudio = { state: "error", error: String(error) };
  document.getElementById("root").textContent = `dbml Studio page failed: ${error}`;
});
