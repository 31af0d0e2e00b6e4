// Minimal stand-in for packages/studio-web (not published to npm): mounts
// @foxglove/studio-base's <App> with in-memory layout storage seeded with the
// layout at data/layout.json (or ?layout=URL) and the usual web data sources.
(async function main() {
  const SB = window.self["@foxglove/studio-base"] || window;  // UMD exports land on root
  const h = React.createElement;
  const params = new URLSearchParams(location.search);
  const layoutUrl = params.get("layout") || "data/layout.json";
  const layoutData = await (await fetch(layoutUrl)).json();

  class MemConfig {
    constructor() { this.values = new Map(); this.listeners = new Map(); }
    get(k) { return this.values.get(k); }
    async set(k, v) { this.values.set(k, v); (this.listeners.get(k) || []).forEach((cb) => cb(v)); }
    addChangeListener(k, cb) { if (!this.listeners.has(k)) this.listeners.set(k, []); this.listeners.get(k).push(cb); }
    removeChangeListener(k, cb) { const l = this.listeners.get(k) || []; const i = l.indexOf(cb); if (i >= 0) l.splice(i, 1); }
  }
  const LAYOUT_ID = "twin-layout";
  const now = new Date().toISOString();
  class MemLayoutStorage {
    constructor() {
      this.ns = new Map();
      this.ns.set("local", new Map([[LAYOUT_ID, {
        id: LAYOUT_ID, name: "twin (imported)", permission: "CREATOR_WRITE",
        baseline: { data: layoutData, savedAt: now }, working: undefined, syncInfo: undefined,
      }]]));
    }
    m(ns) { if (!this.ns.has(ns)) this.ns.set(ns, new Map()); return this.ns.get(ns); }
    async list(ns) { return [...this.m(ns).values()]; }
    async get(ns, id) { return this.m(ns).get(id); }
    async put(ns, layout) { this.m(ns).set(layout.id, layout); return layout; }
    async delete(ns, id) { this.m(ns).delete(id); }
    async importLayouts() {}
  }
  localStorage.setItem("studio.profile-data", JSON.stringify({ currentLayoutId: LAYOUT_ID }));

  SB.installDevtoolsFormatters?.();
  SB.overwriteFetch?.();
  await SB.waitForFonts?.();
  await SB.initI18n?.();

  const dataSources = [
    new SB.Ros1SocketDataSourceFactory(),
    new SB.Ros1LocalBagDataSourceFactory(),
    new SB.Ros2LocalBagDataSourceFactory(),
    new SB.RosbridgeDataSourceFactory(),
    new SB.FoxgloveWebSocketDataSourceFactory(),
    new SB.UlogLocalDataSourceFactory(),
    new SB.McapLocalDataSourceFactory(),
    new SB.RemoteDataSourceFactory(),
  ];
  const app = h(SB.App, {
    deepLinks: [window.location.href],
    appConfiguration: new MemConfig(),
    dataSources,
    layoutStorage: new MemLayoutStorage(),
    extensionLoaders: [],
    enableGlobalCss: true,
  });
  ReactDOM.render(app, document.getElementById("root"));
  window.__studioBooted = true;
})().catch((e) => { console.error("BOOT ERROR", e); document.body.insertAdjacentText("afterbegin", "BOOT ERROR " + e); });
