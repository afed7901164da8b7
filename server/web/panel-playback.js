// @ts-check
// The selected avatar's state and its clip: play (own clips, or another rig's retargeted),
// pause, resume, stop, speed, cross-fade length, loop.

import { $, el, num, notice, describeError } from "./ui.js";
import { yawDegrees } from "./panel-scenes.js";

/** @typedef {import("./ui.js").Ctx} Ctx */
/** @typedef {import("./store.js").State} State */
/** @typedef {import("./protocol.js").AssetInfo} AssetInfo */

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, run } = ctx;
  const select = $("clip-select", HTMLSelectElement);
  /** @type {{assets: AssetInfo[], asset: string | null} | null} */
  let filled = null;
  /** The avatar and clip the picker last showed as playing (`[avatar, clip choice]`). */
  let playing = "";

  store.on(["scenes", "selected", "assets"], (s) => {
    const entry = store.selectedAvatar();
    const dl = $("avatar-state");
    dl.replaceChildren();
    if (!entry) {
      dl.append(el("dt", {}, "Avatar"), el("dd", {}, "none selected"));
      return;
    }
    const a = entry.state;
    const [x, y, z] = a.placement.position;
    /** @type {[string, string][]} */
    const rows = [
      ["Avatar", `${a.avatar} (rig ${a.asset}, scene ${a.scene})`],
      ["Clip", a.clip ? (a.clip_asset ? `${a.clip} (retargeted from ${a.clip_asset})` : a.clip) : "none"],
      ["Speed", String(a.speed)],
      ["State", `${a.paused ? "paused" : "playing"}, ${a.looping ? "looping" : "not looping"}${a.root_motion ? `, root motion ${a.root_motion.replace("_", " ")}` : ""}`],
      ["Overrides", a.overrides.length ? a.overrides.join(", ") : "none"],
      ["Placement", `(${x.toFixed(2)}, ${y.toFixed(2)}, ${z.toFixed(2)}) m, facing ${yawDegrees(a.placement.rotation).toFixed(0)}°`],
    ];
    $("release-drive").hidden = !a.driven;
    $("drive").hidden = !!a.driven;
    if (a.driver) rows.push(["Live", `driven by ${a.driver.name} (${a.driver.via})`]);
    else if (a.driven) rows.push(["Live", "holding a live pose"]);
    if (a.recording) rows.push(["Recording", a.recording]);
    if (a.layers?.length) {
      const shown = a.layers.map(
        (l) => `${l.layer}: ${l.clip}${l.additive ? " (additive)" : ""}, weight ${l.weight.toFixed(2)}, ${l.joints} joints`,
      );
      rows.push(["Layers", shown.join("; ")]);
    }
    for (const [k, v] of rows) dl.append(el("dt", {}, k), el("dd", { dataset: { field: k.toLowerCase() } }, v));

    // The clip list changes with the rig or the assets, not with every state change.
    if (filled?.assets !== s.assets || filled.asset !== a.asset) {
      filled = { assets: s.assets, asset: a.asset };
      const keep = select.value;
      select.replaceChildren();
      const own = s.assets.find((x) => x.name === a.asset);
      const others = s.assets.filter((x) => x.name !== a.asset && x.clips.length);
      /**
       * @param {string} label
       * @param {AssetInfo} asset
       * @param {string | null} from
       */
      const group = (label, asset, from) => {
        const g = el("optgroup", { label });
        for (const c of asset.clips) {
          g.append(el("option", { value: JSON.stringify([from, c.name]) }, `${c.name} (${c.duration.toFixed(2)} s)`));
        }
        return g;
      };
      if (own) select.append(group(`${own.name} (own clips)`, own, null));
      for (const x of others) select.append(group(`Retargeted from ${x.name}`, x, x.name));
      const offered = [...select.options].map((o) => o.value);
      if (offered.includes(keep)) select.value = keep;
    }
    // The picker shows what plays: when another avatar is selected, or its clip changes (a
    // play from this page or anyone else's), it moves to that clip; a choice not yet played
    // stays until then.
    const current = JSON.stringify([a.clip_asset ?? null, a.clip]);
    const now = JSON.stringify([a.avatar, current]);
    if (now !== playing && [...select.options].some((o) => o.value === current)) {
      select.value = current;
      playing = now;
    }
  });

  $("play").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    if (!entry || !select.value) return;
    const [from, clip] = /** @type {[string | null, string]} */ (JSON.parse(select.value));
    const avatar = entry.state.avatar;
    /** @type {import("./protocol.js").Command} */
    const command = {
      op: "play",
      avatar,
      clip,
      speed: num("speed", 1),
      looping: $("looping", HTMLInputElement).checked,
      fade: num("fade", 0.25),
    };
    if (from) command.from_asset = from;
    run(command).then(() => notice(`Playing ${from ? `${from}:` : ""}${clip} on ${avatar}`), () => {});
  });
  // Clip layers: the chosen clip over the avatar's clip, on the joints named (each joint's
  // subtree; `-name` takes a subtree out), replacing or additive.
  $("play-layer").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    const layer = $("layer-name", HTMLInputElement).value.trim();
    if (!entry || !select.value || !layer) return;
    const [from, clip] = /** @type {[string | null, string]} */ (JSON.parse(select.value));
    const avatar = entry.state.avatar;
    const names = $("layer-mask", HTMLInputElement)
      .value.split(/[\s,]+/)
      .filter((n) => n.length > 0);
    const joints = names.filter((n) => !n.startsWith("-"));
    const except = names.filter((n) => n.startsWith("-")).map((n) => n.slice(1));
    /** @type {import("./protocol.js").Command} */
    const command = {
      op: "play_layer",
      avatar,
      layer,
      clip,
      additive: $("layer-additive", HTMLInputElement).checked,
      weight: Math.min(1, Math.max(0, num("layer-weight", 1))),
      speed: num("speed", 1),
      looping: $("looping", HTMLInputElement).checked,
      fade: num("fade", 0.25),
    };
    if (joints.length) command.mask = except.length ? { joints, except } : { joints };
    if (from) command.from_asset = from;
    run(command).then(() => notice(`${avatar} plays ${clip} on layer ${layer}.`), () => {});
  });
  $("stop-layer").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    const layer = $("layer-name", HTMLInputElement).value.trim();
    if (!entry || !layer) return;
    const avatar = entry.state.avatar;
    run({ op: "stop_layer", avatar, layer, fade: num("fade", 0.25) }).then(
      () => notice(`Layer ${layer} of ${avatar} fades out.`),
      () => {},
    );
  });
  for (const op of /** @type {const} */ (["pause", "resume", "stop"])) {
    $(op).addEventListener("click", () => {
      const entry = store.selectedAvatar();
      if (entry) run({ op, avatar: entry.state.avatar }).catch(() => {});
    });
  }
  // Recording: a take of the selected avatar becomes a clip of its rig, downloadable as glTF
  // or BVH once stopped.
  $("record").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    const clip = $("take-name", HTMLInputElement).value.trim();
    if (!entry || !clip) return;
    const avatar = entry.state.avatar;
    run({ op: "record", avatar, clip }).then(() => notice(`Recording ${clip} of ${avatar}…`), () => {});
  });
  $("stop-recording").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    if (!entry) return;
    const { avatar, asset } = entry.state;
    run({ op: "stop_recording", avatar }).then((result) => {
      // The ack's `recorded` result: the rig the clip went to and its name.
      const r = /** @type {{asset?: string, clip?: string}} */ (result ?? {});
      const clip = r.clip ?? entry.state.recording ?? "";
      const rig = r.asset ?? asset;
      const base = `/api/assets/${encodeURIComponent(rig)}/clips/${encodeURIComponent(clip)}`;
      const links = $("take-links");
      links.replaceChildren(
        `Take ${clip}: download `,
        el("a", { href: `${base}.glb`, download: `${clip}.glb`, dataset: { take: "glb" } }, "glTF"),
        " · ",
        el("a", { href: `${base}.bvh`, download: `${clip}.bvh`, dataset: { take: "bvh" } }, "BVH"),
      );
      links.hidden = false;
      notice(`Recorded ${clip} of ${avatar}.`);
    }, () => {});
  });
  // Ends whoever drives the avatar live (a websocket driver, a VMC input, a held pose): it
  // plays its clip again.
  $("release-drive").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    if (!entry) return;
    const avatar = entry.state.avatar;
    if (ctx.drive.avatar === avatar) store.set({ driving: null });
    const released = ctx.drive.avatar === avatar ? ctx.drive.release() : run({ op: "release_drive", avatar });
    released.then(
      () => notice(`${avatar} released: its clip plays again.`),
      (e) => notice(`release_drive failed — ${describeError(e)}`, "error"),
    );
  });
  // The page drives the avatar live: it holds the pose it has now (every joint's streamed
  // local rotation), and the joint sliders set rotations in that live pose.
  $("drive").addEventListener("click", async () => {
    const entry = store.selectedAvatar();
    const desc = store.get().descriptions.get(store.get().selected ?? "");
    const pose = store.get().poses.get(store.get().selected ?? "");
    if (!entry || !desc || !pose) return;
    const avatar = entry.state.avatar;
    /** @type {Record<string, import("./protocol.js").Quat>} */
    const rotations = {};
    desc.joint_names.forEach((name, j) => {
      const q = pose.rotations[j];
      if (q) rotations[name] = q;
    });
    try {
      await ctx.drive.start(avatar, rotations);
    } catch (e) {
      notice(`drive failed — ${describeError(e)}`, "error");
      return;
    }
    store.set({ driving: avatar });
    notice(`The page drives ${avatar}: pick a joint and move its sliders.`);
  });
  $("set-speed").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    if (entry) run({ op: "set_speed", avatar: entry.state.avatar, speed: num("speed", 1) }).catch(() => {});
  });
}
