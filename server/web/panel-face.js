// @ts-check
// The selected avatar's face: its morph channels as sliders (`set_morph_weights`, the weight of
// one channel per move), a standard expression by name (`set_expression`: ARKit, VRM presets and
// visemes the server found on the rig) and Neutral (every weight to 0). The sliders follow the
// weights the avatar shows — its newest streamed frame's (protocol version 4), else its state —
// unless one is being moved.

import { $, el, notice } from "./ui.js";

/** @typedef {import("./ui.js").Ctx} Ctx */
/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, run, conn } = ctx;
  const sliders = $("face-sliders");
  const picker = $("face-expression", HTMLSelectElement);
  /** @type {string} The description hash the controls were built for. */
  let builtFor = "";
  /** @type {Map<string, HTMLInputElement>} Channel → its slider. */
  const inputs = new Map();

  const selectedDesc = () => store.get().descriptions.get(store.get().selected ?? "") ?? null;

  /** @param {AvatarDescription | null} desc */
  const build = (desc) => {
    builtFor = desc?.hash ?? "";
    sliders.replaceChildren();
    inputs.clear();
    picker.replaceChildren();
    const channels = desc?.morph_targets ?? [];
    $("face-now").textContent = !desc
      ? ""
      : channels.length === 0
        ? `${desc.id}'s rig has no morph targets: it shows no expressions.`
        : `${channels.length} morph channels; ${(desc.expression_binds ?? []).length} expressions from the file; ${Object.keys(desc.expressions ?? {}).length} standard names map onto them.`;
    for (const channel of channels) {
      const input = el("input", { type: "range", min: "0", max: "1", step: "0.01", value: "0", id: `face-${channel}` });
      const slider = /** @type {HTMLInputElement} */ (input);
      slider.setAttribute("aria-label", channel);
      slider.dataset.channel = channel;
      slider.addEventListener("input", () => {
        const avatar = store.get().selected;
        if (!avatar) return;
        run({ op: "set_morph_weights", avatar, weights: { [channel]: Number(slider.value) } }).catch(() => {});
      });
      inputs.set(channel, slider);
      sliders.append(el("div", { className: "row" }, el("label", { htmlFor: slider.id }, channel), slider));
    }
    // The file's own expressions (a VRM's: weighted channels, overrides) first, then the
    // standard names found among the channels.
    for (const e of desc?.expression_binds ?? []) {
      const binds = e.binds.map((b) => (b.weight === 1 ? b.channel : `${b.channel}×${b.weight}`)).join(" + ");
      picker.append(el("option", { value: e.name }, `${e.name} → ${binds}${e.is_binary ? " (binary)" : ""}`));
    }
    for (const [name, channel] of Object.entries(desc?.expressions ?? {}).sort(([a], [b]) => a.localeCompare(b))) {
      picker.append(el("option", { value: name }, `${name} → ${channel}`));
    }
    $("face-controls", HTMLFieldSetElement).hidden = channels.length === 0;
  };

  /** Shows the avatar's weights on the sliders not being dragged. */
  const follow = () => {
    const entry = store.selectedAvatar();
    const streamed = entry ? conn.latest(entry.state.avatar)?.weights : undefined;
    const weights = streamed ?? entry?.state.morph_weights ?? {};
    for (const [channel, input] of inputs) {
      if (document.activeElement === input) continue;
      input.value = String(weights[channel] ?? 0);
    }
  };

  store.on(["selected", "descriptions"], () => {
    const desc = selectedDesc();
    if ((desc?.hash ?? "") !== builtFor || !desc) build(desc);
    follow();
  });
  store.on(["scenes"], follow);
  // Weights change with every frame of a talking face: a few times a second is enough here.
  setInterval(() => {
    if (inputs.size > 0) follow();
  }, 200);

  $("face-expression-set").addEventListener("click", () => {
    const avatar = store.get().selected;
    if (!avatar || !picker.value) return;
    const weight = Math.min(1, Math.max(0, Number($("face-expression-weight", HTMLInputElement).value) || 0));
    run({ op: "set_expression", avatar, expression: picker.value, weight }).then(
      () => notice(`${avatar} shows ${picker.value} at ${weight}.`),
      () => {},
    );
  });
  $("face-reset").addEventListener("click", () => {
    const avatar = store.get().selected;
    if (!avatar) return;
    run({ op: "set_morph_weights", avatar, weights: {}, reset: true }).then(() => notice(`${avatar}'s face is neutral.`), () => {});
  });
}
