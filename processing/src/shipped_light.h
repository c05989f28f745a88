// Tests: the light model of the shipped rig (168 units, fastage-38).
#pragma once

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/processing/light_model.h"

namespace stage::processing {

inline LightModel ShippedLight() {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok());
  auto light = LightModel::FromRig(*rig);
  EXPECT_TRUE(light.ok()) << light.status();
  return *light;
}

}  // namespace stage::processing
