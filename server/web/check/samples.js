// @ts-check
// Written by tests/web/samples.rs from the Rust protocol types (POSECAST_UPDATE_WEB_SAMPLES=1
// rewrites it; the test fails when it is out of date). Each sample satisfies its JSDoc
// type in ../protocol.js: tsc (scripts/check-web) fails on a field missing, extra or of
// another type. Not served; nothing imports it.

export const welcome = /** @satisfies {import("../protocol.js").WelcomeMsg} */ ({
  "access": {
    "avatars": [
      "alice"
    ],
    "control": true,
    "expires_at": 1763894600,
    "name": "alice",
    "rights": [
      "view",
      "control",
      "drive"
    ],
    "scenes": [
      "lobby"
    ],
    "view": true
  },
  "encoding": "json",
  "server": "posecast 0.1.0",
  "server_time_us": 1763891000000000,
  "tick_rate": 60.0,
  "type": "welcome",
  "version": 1
});

export const subscribed = /** @satisfies {import("../protocol.js").SubscribedMsg} */ ({
  "joints": {
    "depth": 3
  },
  "rate": 20.0,
  "scene": "lobby",
  "scene_num": 2,
  "type": "subscribed"
});

export const unsubscribed = /** @satisfies {import("../protocol.js").UnsubscribedMsg} */ ({
  "scene": "lobby",
  "type": "unsubscribed"
});

export const description = /** @satisfies {import("../protocol.js").DescriptionMsg} */ ({
  "avatar": {
    "clip": "walk",
    "expressions": {
      "aa": "mouthOpen",
      "blink": "eyesClosed"
    },
    "hash": "0123456789abcdef",
    "id": "guest",
    "inverse_binds": [
      [
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0
      ],
      [
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0
      ]
    ],
    "joint_names": [
      "root",
      "spine"
    ],
    "mesh_url": "/api/assets/avatar/mesh.glb",
    "morph_targets": [
      "mouthOpen",
      "eyesClosed"
    ],
    "name": "avatar",
    "num": 7,
    "parents": [
      -1,
      0
    ],
    "rest_rotations": [
      [
        0.0,
        0.0,
        0.0,
        1.0
      ],
      [
        0.0,
        0.0,
        0.0,
        1.0
      ]
    ],
    "rest_scales": [
      [
        1.0,
        1.0,
        1.0
      ],
      [
        1.0,
        1.0,
        1.0
      ]
    ],
    "rest_translations": [
      [
        0.0,
        0.8999999761581421,
        0.0
      ],
      [
        0.0,
        0.10000000149011612,
        0.0
      ]
    ],
    "scaled_joints": [
      1
    ],
    "translated_joints": [
      0
    ]
  },
  "scene": "lobby",
  "type": "description"
});

export const avatarRemoved = /** @satisfies {import("../protocol.js").AvatarRemovedMsg} */ ({
  "avatar": "guest",
  "scene": "lobby",
  "type": "avatar_removed"
});

export const scenes = /** @satisfies {import("../protocol.js").ScenesMsg} */ ({
  "scenes": [
    {
      "avatars": [
        {
          "asset": "avatar",
          "avatar": "guest",
          "blend_shapes": {
            "joy": 0.5
          },
          "clip": "walk",
          "clip_asset": "01_01",
          "driven": true,
          "driver": {
            "name": "alice",
            "via": "websocket"
          },
          "fade": {
            "duration": 0.30000001192092896,
            "elapsed": 0.10000000149011612,
            "from": "idle",
            "from_asset": "other"
          },
          "ik_goals": [
            "l_wrist"
          ],
          "layers": [
            {
              "additive": false,
              "clip": "wave",
              "joints": 12,
              "layer": "upper",
              "speed": 1.0,
              "time": 0.75,
              "weight": 1.0
            }
          ],
          "looking": true,
          "looping": true,
          "morph_weights": {
            "mouthOpen": 0.25
          },
          "overrides": [
            "l_elbow"
          ],
          "paused": false,
          "placement": {
            "position": [
              2.0,
              0.0,
              -1.0
            ],
            "rotation": [
              0.0,
              0.38291096687316895,
              0.0,
              0.9237852692604065
            ]
          },
          "recording": "take",
          "root_motion": "accumulate",
          "scene": "lobby",
          "speed": 1.5,
          "time": 0.5
        }
      ],
      "scene": "lobby",
      "subscribers": 3,
      "viewers": [
        {
          "connections": 2,
          "name": "alice"
        },
        {
          "connections": 1,
          "name": null
        }
      ]
    }
  ],
  "type": "scenes"
});

export const viewers = /** @satisfies {import("../protocol.js").ViewersMsg} */ ({
  "scene": "lobby",
  "type": "viewers",
  "viewers": [
    {
      "connections": 1,
      "name": "alice"
    }
  ]
});

export const sceneCreated = /** @satisfies {import("../protocol.js").SceneCreatedMsg} */ ({
  "scene": "lobby",
  "type": "scene_created"
});

export const sceneDeleted = /** @satisfies {import("../protocol.js").SceneDeletedMsg} */ ({
  "scene": "lobby",
  "type": "scene_deleted"
});

export const avatarChanged = /** @satisfies {import("../protocol.js").AvatarChangedMsg} */ ({
  "avatar": {
    "asset": "avatar",
    "avatar": "guest",
    "clip": "walk",
    "clip_asset": null,
    "looping": true,
    "overrides": [
      "l_elbow"
    ],
    "paused": false,
    "placement": {
      "position": [
        2.0,
        0.0,
        -1.0
      ],
      "rotation": [
        0.0,
        0.38291096687316895,
        0.0,
        0.9237852692604065
      ]
    },
    "scene": "lobby",
    "speed": 1.5,
    "time": 0.5
  },
  "scene": "lobby",
  "seq": 5120,
  "type": "avatar_changed"
});

export const pong = /** @satisfies {import("../protocol.js").PongMsg} */ ({
  "client_time_us": 1763891000000000,
  "id": 3,
  "server_time_us": 1763891000000500,
  "type": "pong"
});

export const ack = /** @satisfies {import("../protocol.js").AckMsg} */ ({
  "id": 4,
  "kind": "avatar_added",
  "result": {
    "avatar": "guest"
  },
  "type": "ack"
});

export const ackNull = /** @satisfies {import("../protocol.js").AckMsg} */ ({
  "id": 5,
  "kind": "done",
  "result": null,
  "type": "ack"
});

export const frame = /** @satisfies {import("../protocol.js").FrameMsg} */ ({
  "avatars": [
    {
      "avatar": "guest",
      "hash": "0123456789abcdef",
      "joints": [
        0,
        1
      ],
      "placement": {
        "position": [
          0.0,
          0.0,
          0.0
        ],
        "rotation": [
          0.0,
          0.0,
          0.0,
          1.0
        ]
      },
      "rotations": [
        [
          0.0,
          0.0,
          0.0,
          1.0
        ],
        [
          0.0,
          0.0,
          0.0,
          1.0
        ]
      ],
      "scales": [
        [
          1.0,
          1.0,
          1.0
        ]
      ],
      "translations": [
        [
          0.0,
          0.8999999761581421,
          0.0
        ]
      ],
      "weights": {
        "eyesClosed": 0.0,
        "mouthOpen": 0.25
      }
    }
  ],
  "scene": "lobby",
  "seq": 5121,
  "server_time_us": 1763891000016667,
  "type": "frame"
});

export const error = /** @satisfies {import("../protocol.js").ErrorMsg} */ ({
  "code": "rate_limited",
  "id": 12,
  "message": "too many commands: try again in 5 ms",
  "retry_after_ms": 5,
  "type": "error"
});

export const error_details = /** @satisfies {import("../protocol.js").ErrorMsg} */ ({
  "code": "unknown_clip",
  "details": {
    "asset": "avatar",
    "clip": "jump"
  },
  "id": 13,
  "message": "rig avatar has no clip jump",
  "type": "error"
});

export const assets = /** @satisfies {import("../protocol.js").AssetInfo[]} */ ([
  {
    "clips": [
      {
        "duration": 1.0,
        "name": "walk"
      }
    ],
    "humanoid": true,
    "joints": 23,
    "mapped": 23,
    "name": "avatar",
    "notes": [
      "material skin not imported"
    ],
    "pipeline": [
      "normalised"
    ]
  }
]);

export const joint = /** @satisfies {import("../protocol.js").JointInfo} */ ({
  "dofs": [
    {
      "max": null,
      "min": -2.0,
      "value": -2.0
    }
  ],
  "joint": "knee_r",
  "joint_type": "ball_euler",
  "overridden": false,
  "parent": "hip_r",
  "rotation": [
    -0.8410000205039978,
    0.0,
    0.0,
    0.5400000214576721
  ]
});

export const hello = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "client": "posecast-dashboard",
  "encoding": "json",
  "token": "s3cret-control-token",
  "type": "hello",
  "version": 1
});

export const subscribe = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "avatars": [
    "guest"
  ],
  "joints": {
    "names": [
      "Head"
    ]
  },
  "morph_weights": false,
  "precision": {
    "degrees": 0.10000000149011612,
    "millimetres": 2.0,
    "translation": 0.0010000000474974513
  },
  "rate": 20.0,
  "scene": "lobby",
  "type": "subscribe"
});

export const watchScenes = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "type": "watch_scenes"
});

export const unwatchScenes = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "type": "unwatch_scenes"
});

export const ping = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "client_time_us": 1763891000000000,
  "id": 1,
  "type": "ping"
});

export const addAvatar = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "command": {
    "asset": "avatar",
    "avatar": "guest",
    "clip": "walk",
    "op": "add_avatar",
    "position": [
      1.0,
      0.0,
      0.0
    ],
    "rotation": [
      0.0,
      0.7070000171661377,
      0.0,
      0.7070000171661377
    ],
    "scene": "lobby"
  },
  "id": 1,
  "type": "command"
});

export const placeAvatar = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "command": {
    "avatar": "guest",
    "duration": 1.5,
    "op": "place_avatar",
    "position": [
      2.0,
      0.0,
      0.5
    ],
    "rotation": [
      0.0,
      0.0,
      0.0,
      1.0
    ]
  },
  "id": 2,
  "type": "command"
});

export const play = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "command": {
    "avatar": "guest",
    "clip": "walk",
    "fade": 0.30000001192092896,
    "from_asset": "01_01",
    "looping": true,
    "op": "play",
    "root_motion": "in_place",
    "speed": 1.5,
    "start": 0.20000000298023224
  },
  "id": 3,
  "type": "command"
});

export const setJointDofs = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "command": {
    "avatar": "guest",
    "joint": "knee_r",
    "op": "set_joint_dofs",
    "values": [
      0.30000001192092896,
      0.0,
      0.0
    ]
  },
  "id": 4,
  "type": "command"
});

export const release = /** @satisfies {import("../protocol.js").ClientMsg} */ ({
  "command": {
    "avatar": "guest",
    "joint": "knee_r",
    "op": "release"
  },
  "id": 5,
  "type": "command"
});
