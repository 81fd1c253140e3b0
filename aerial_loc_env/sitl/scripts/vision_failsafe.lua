-- Vision-fix failsafe for ArduPlane navigating on a vision companion's fix (GPS_INPUT as its GPS).
--
-- ArduPlane has no failsafe of its own for a lost position fix in fixed-wing flight: its EKF failsafe acts only
-- in VTOL modes, and the advanced failsafe (AFS_*) would also fire below the camera's range on every final. This
-- script does what the plane should: in AUTO on a waypoint, outside the landing sequence, when the primary GPS has
-- had a 3D fix on a waypoint since arming (the fix was there and went: not the acquisition during the climb-out)
-- and then none for LOSS_MS, it switches to LOITER (circling where it is, on dead reckoning, instead of flying on across
-- the map blind) and says so; when the fix has been back for BACK_MS it returns to AUTO, which resumes the
-- mission at the waypoint it was flying to. On the landing sequence (from DO_LAND_START on) it only reports:
-- the final is flown on dead reckoning below the camera's range anyway, and a go-around without a fix is worse.

local MODE_AUTO = 10
local MODE_LOITER = 12
local LOSS_MS = 1000
local BACK_MS = 2000
local DO_LAND_START = 189
local NAV_WAYPOINT = 16
local SEVERITY_CRITICAL = 2
local SEVERITY_WARNING = 4
local SEVERITY_INFO = 6

local lost_since = nil
local back_since = nil
local acting = false
local reported = false
local had_fix = false      -- a 3D fix seen while flying a waypoint since arming

local function landing_start_index()
  for i = 1, mission:num_commands() - 1 do
    local item = mission:get_item(i)
    if item and item:command() == DO_LAND_START then
      return i
    end
  end
  return nil
end

local function on_landing_sequence()
  local land = landing_start_index()
  return land ~= nil and mission:get_current_nav_index() >= land
end

local function update()
  local now = millis():toint()
  if not arming:is_armed() then
    lost_since, back_since, acting, reported, had_fix = nil, nil, false, false, false
    return update, 200
  end
  local fix = gps:status(gps:primary_sensor()) >= 3
  if fix and mission:get_current_nav_id() == NAV_WAYPOINT then
    had_fix = true
  end
  if not fix then
    back_since = nil
    lost_since = lost_since or now
    if had_fix and not acting and not reported and now - lost_since >= LOSS_MS
        and vehicle:get_mode() == MODE_AUTO then
      if on_landing_sequence() then
        gcs:send_text(SEVERITY_WARNING, "Vision failsafe: fix lost landing, landing on")
        reported = true
      elseif mission:get_current_nav_id() == NAV_WAYPOINT then
        if vehicle:set_mode(MODE_LOITER) then
          acting = true
          gcs:send_text(SEVERITY_CRITICAL, "Vision failsafe: fix lost, LOITER")
        end
      end
    end
  else
    lost_since = nil
    reported = false
    if acting then
      back_since = back_since or now
      if now - back_since >= BACK_MS then
        acting = false
        if vehicle:get_mode() == MODE_LOITER and vehicle:set_mode(MODE_AUTO) then
          gcs:send_text(SEVERITY_INFO, "Vision failsafe: fix back, AUTO")
        end
      end
    end
  end
  return update, 100
end

gcs:send_text(SEVERITY_INFO, "Vision failsafe loaded")
return update, 1000
