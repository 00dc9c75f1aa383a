-- Releasing leases, shared by the scripts that release them (prepended to release.lua and commit.lua: the
-- function below is theirs).

-- Release one lock or claim key if it still holds this token (never another holder's), and wake a waiter
-- if someone waits for it (acquire.lua marked it <key>:wanted): a token on <key>:wake, the list the waiter
-- blocks on (BLPOP), at most one token a list, for 1 s (one unclaimed costs a later waiter one retry).
-- Blocked clients are served in the order they blocked. Returns 1 when released, else 0.
local function release_lease(key, token)
  if redis.call('GET', key) ~= token then
    return 0
  end
  redis.call('DEL', key)
  if redis.call('EXISTS', key .. ':wanted') == 1 then
    local wake = key .. ':wake'
    redis.call('RPUSH', wake, 1)
    redis.call('LTRIM', wake, -1, -1)
    redis.call('PEXPIRE', wake, 1000)
  end
  return 1
end
