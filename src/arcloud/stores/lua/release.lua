-- Release the keys still held with this token (never another holder's).
-- KEYS: the lock/claim keys. ARGV[1]: token. Returns how many were released.
local released = 0
for _, key in ipairs(KEYS) do
  if redis.call('GET', key) == ARGV[1] then
    redis.call('DEL', key)
    released = released + 1
  end
end
return released
