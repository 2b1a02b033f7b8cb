// Hosts Foxglove Studio's app with an in-memory layout: a 3D panel following the rover (display
// frame `world`, the topics the page is given in window.ROVER_TWIN_TOPICS made visible) beside
// the head camera's left image. The run comes from the URL (`ds=remote-file&ds.url=...`).
(function () {
  const S = window; // the UMD bundle puts its exports on the window
  const topics = {};
  for (const t of window.ROVER_TWIN_TOPICS || []) topics[t] = { visible: true };
  const threeD = {
    cameraState: { distance: 16, perspective: true, phi: 50, target: [0, 0, 0], targetOffset: [0, 0, 0],
      targetOrientation: [0, 0, 0, 1], thetaOffset: 150, fovy: 45, near: 0.5, far: 5000 },
    followMode: "follow-position", followTf: "base_link",
    scene: { transforms: { showLabel: false, axisScale: 0.001, lineWidth: 0 } },
    transforms: {}, topics, layers: {}, publish: {}, imageMode: {},
  };
  const data = {
    configById: {
      "3D!rover": threeD,
      "ImageViewPanel!head": { cameraTopic: window.ROVER_TWIN_IMAGE || "/sensors/head_stereo/left" },
    },
    globalVariables: {}, userNodes: {}, playbackConfig: { speed: 1 },
    layout: { first: "3D!rover", second: "ImageViewPanel!head", direction: "row", splitPercentage: 68 },
  };
  const layout = { id: "rover-twin", name: "rover-twin", permission: "CREATOR_WRITE",
    baseline: { data, savedAt: undefined }, working: undefined, syncInfo: undefined };
  const layouts = new Map([[layout.id, layout]]);
  const layoutStorage = {
    list: async () => [...layouts.values()],
    get: async (_ns, id) => layouts.get(id),
    put: async (_ns, l) => { layouts.set(l.id, l); return l; },
    delete: async (_ns, id) => { layouts.delete(id); },
    importLayouts: async () => {},
  };
  const values = new Map();
  const appConfiguration = {
    get: (k) => values.get(k),
    set: async (k, v) => { values.set(k, v); },
    addChangeListener: () => {}, removeChangeListener: () => {},
  };
  S.initI18n().then(() => {
    const app = React.createElement(S.App, {
      deepLinks: [window.location.href],
      appConfiguration,
      dataSources: [new S.RemoteDataSourceFactory(), new S.McapLocalDataSourceFactory()],
      layoutStorage,
      extensionLoaders: [],
      enableGlobalCss: true,
    });
    ReactDOM.render(app, document.getElementById("root"));
  });
})();
